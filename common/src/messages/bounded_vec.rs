//! Deserializing a `Vec` whose length prefix is untrusted.
//!
//! bincode's serde path does not charge sequence lengths against its byte limit,
//! and serde's own `Vec` preallocates up to 1 MiB from the length prefix alone.
//! This visitor refuses, before allocating anything, a length whose elements
//! could not fit in [`DECODE_CLAIM_LIMIT_BYTES`] (each element of our vectors
//! claims `size_of::<T>()` bytes of the limit when decoded, so such a message
//! would fail anyway), and preallocates at most [`MAX_PREALLOC_ELEMENTS`].

use std::fmt;
use std::marker::PhantomData;

use serde::de::{Deserialize, Deserializer, Error, SeqAccess, Visitor};

use super::codec::DECODE_CLAIM_LIMIT_BYTES;

/// Largest capacity reserved from a length prefix; longer vectors grow as
/// their elements actually arrive.
pub(crate) const MAX_PREALLOC_ELEMENTS: usize = 4096;

/// The longest sequence of `T` that fits in the decode limit.
pub(crate) fn max_len<T>() -> usize {
    DECODE_CLAIM_LIMIT_BYTES / std::mem::size_of::<T>().max(1)
}

/// `#[serde(deserialize_with = "bounded_vec::deserialize")]` for `Vec<T>` fields.
pub(crate) fn deserialize<'de, D, T>(deserializer: D) -> Result<Vec<T>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    deserializer.deserialize_seq(BoundedVecVisitor(PhantomData))
}

struct BoundedVecVisitor<T>(PhantomData<T>);

impl<'de, T: Deserialize<'de>> Visitor<'de> for BoundedVecVisitor<T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a sequence of at most {} elements", max_len::<T>())
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        let max = max_len::<T>();
        let hint = seq.size_hint().unwrap_or(0);
        if hint > max {
            return Err(A::Error::invalid_length(hint, &self));
        }
        let mut out = Vec::with_capacity(hint.min(MAX_PREALLOC_ELEMENTS));
        while let Some(element) = seq.next_element()? {
            if out.len() >= max {
                return Err(A::Error::invalid_length(out.len() + 1, &self));
            }
            out.push(element);
        }
        Ok(out)
    }
}
