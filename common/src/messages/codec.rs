//! The wire format: `b"FVIO"`, a little-endian `u16` version, then the bincode
//! 2 (serde, standard configuration: little-endian, varint integers) encoding
//! of the [`Envelope`].
//!
//! Decoding trusts nothing: the size is checked first, bincode runs with a byte
//! limit, length prefixes are bounded before anything is allocated, the whole
//! input must be consumed, and the content is validated.

use thiserror::Error;

use super::envelope::Envelope;
use super::validate::{Limits, ValidationError};

/// The first four bytes of every message.
pub const MAGIC: [u8; 4] = *b"FVIO";

/// The wire version this build writes. Version 2: a snapshot's covariance may
/// end with the sender's camera intrinsics (version 1 peers would misread it).
/// Version 3: heartbeats carry the newest keyframe window's end time, and the
/// history catch-up messages exist (version 2 peers would misread heartbeats).
/// Version 4: a history answer lists the windows it was made of, so a
/// requester can tell which replays it lost. Version 5: a request lists the
/// windows held short of some parts, and a replay may carry only those parts;
/// heartbeats may say `Settled`. Version 6: a snapshot names the world frame
/// its poses are in (`frame_epoch`). Version 7: a snapshot carries its
/// sender's pixel noise (`pixel_sigma_px`).
pub const WIRE_VERSION: u16 = 7;

/// The wire versions this build reads.
pub const SUPPORTED_VERSIONS: &[u16] = &[WIRE_VERSION];

/// Bytes before the bincode payload: magic and version.
pub const HEADER_LEN: usize = MAGIC.len() + 2;

/// bincode's decode limit, in bytes of the decoded values' in-memory sizes
/// (each integer counts its full width even when its varint took one byte, a
/// string or `Vec<u8>` counts its length before it is allocated). It caps what
/// any length prefix can make the decoder allocate. The largest valid message
/// under the default [`Limits`] (a 64-clone snapshot with 1024 landmarks)
/// claims about 0.35 MiB, well below it; [`Limits`] far above the defaults
/// (hundreds of clones) would reach it and fail with [`DecodeError::LimitExceeded`].
pub const DECODE_CLAIM_LIMIT_BYTES: usize = 4 << 20;

/// bincode's standard configuration with the decode limit.
fn decode_config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<DECODE_CLAIM_LIMIT_BYTES>()
}

/// Why a message could not be encoded.
#[derive(Debug, Error)]
pub enum EncodeError {
    /// The content is invalid; peers would reject it.
    #[error("refusing to encode an invalid message: {0}")]
    Invalid(#[from] ValidationError),
    /// The encoded message is larger than peers accept.
    #[error("encoded message is {len} bytes, larger than the limit of {max} bytes")]
    TooLarge {
        /// Encoded size, header included.
        len: usize,
        /// [`Limits::max_message_bytes`].
        max: usize,
    },
    /// bincode failed (not expected for these types).
    #[error("bincode encoding failed: {0}")]
    Bincode(#[from] bincode::error::EncodeError),
}

/// Why bytes could not be decoded into a valid message.
#[derive(Debug, Error)]
pub enum DecodeError {
    /// The input is larger than [`Limits::max_message_bytes`].
    #[error("message of {len} bytes exceeds the limit of {max} bytes")]
    TooLarge {
        /// Input size.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// The input is shorter than the header.
    #[error("message of {len} bytes is shorter than the {HEADER_LEN}-byte header")]
    TooShort {
        /// Input size.
        len: usize,
    },
    /// The input does not start with [`MAGIC`].
    #[error("bad magic {found:02x?}: expected {MAGIC:02x?} (\"FVIO\")")]
    BadMagic {
        /// The first four bytes.
        found: [u8; 4],
    },
    /// The wire version is not one this build reads.
    #[error("unsupported wire version {found}; this build reads versions {supported:?}")]
    UnsupportedVersion {
        /// The version in the header.
        found: u16,
        /// [`SUPPORTED_VERSIONS`].
        supported: &'static [u16],
    },
    /// Decoding would claim more than [`DECODE_CLAIM_LIMIT_BYTES`] (a huge length
    /// prefix, or too much content).
    #[error("message would decode to more than the limit of {limit} bytes")]
    LimitExceeded {
        /// [`DECODE_CLAIM_LIMIT_BYTES`].
        limit: usize,
    },
    /// The payload is not a bincode envelope.
    #[error("malformed payload: {0}")]
    Malformed(#[source] bincode::error::DecodeError),
    /// Bytes remain after the envelope.
    #[error("{count} trailing bytes after the envelope")]
    TrailingBytes {
        /// How many.
        count: usize,
    },
    /// The envelope decoded but its content is invalid.
    #[error("invalid message: {0}")]
    Invalid(#[from] ValidationError),
}

/// Encodes a message with the default [`Limits`].
pub fn encode(env: &Envelope) -> Result<Vec<u8>, EncodeError> {
    encode_with(env, &Limits::default())
}

/// Encodes a message, refusing one that is invalid under `limits` or larger
/// than `limits.max_message_bytes` (peers would reject it).
pub fn encode_with(env: &Envelope, limits: &Limits) -> Result<Vec<u8>, EncodeError> {
    env.validate(limits)?;
    let mut out = Vec::with_capacity(256);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&WIRE_VERSION.to_le_bytes());
    bincode::serde::encode_into_std_write(env, &mut out, bincode::config::standard())?;
    if out.len() > limits.max_message_bytes {
        return Err(EncodeError::TooLarge {
            len: out.len(),
            max: limits.max_message_bytes,
        });
    }
    Ok(out)
}

/// Decodes a message with the default [`Limits`].
pub fn decode(bytes: &[u8]) -> Result<Envelope, DecodeError> {
    decode_with(bytes, &Limits::default())
}

/// Decodes and validates a message from untrusted bytes. Never panics.
///
/// In order: the size (at most `limits.max_message_bytes`), the header (magic,
/// a version in [`SUPPORTED_VERSIONS`]), the bincode payload (bounded by
/// [`DECODE_CLAIM_LIMIT_BYTES`], no trailing bytes), then the content
/// ([`Envelope::validate`]): every float finite, the fleet id non-empty, at
/// most [`super::MAX_FLEET_ID_BYTES`] bytes and free of key-expression
/// characters, list lengths within `limits`, a snapshot's covariance of side
/// `6 · clones` with `dim (dim + 1) / 2` entries and a positive diagonal,
/// clone quaternions of unit norm (within [`super::QUATERNION_NORM_TOLERANCE`])
/// and clone times non-decreasing, landmark variances positive, and a valid
/// camera model.
pub fn decode_with(bytes: &[u8], limits: &Limits) -> Result<Envelope, DecodeError> {
    if bytes.len() > limits.max_message_bytes {
        return Err(DecodeError::TooLarge {
            len: bytes.len(),
            max: limits.max_message_bytes,
        });
    }
    let (header, payload) = match (bytes.get(..HEADER_LEN), bytes.get(HEADER_LEN..)) {
        (Some(h), Some(p)) => (h, p),
        _ => return Err(DecodeError::TooShort { len: bytes.len() }),
    };
    let found = [header[0], header[1], header[2], header[3]];
    if found != MAGIC {
        return Err(DecodeError::BadMagic { found });
    }
    let version = u16::from_le_bytes([header[4], header[5]]);
    if !SUPPORTED_VERSIONS.contains(&version) {
        return Err(DecodeError::UnsupportedVersion {
            found: version,
            supported: SUPPORTED_VERSIONS,
        });
    }
    let (env, used): (Envelope, usize) =
        bincode::serde::decode_from_slice(payload, decode_config()).map_err(|e| match e {
            bincode::error::DecodeError::LimitExceeded => DecodeError::LimitExceeded {
                limit: DECODE_CLAIM_LIMIT_BYTES,
            },
            other => DecodeError::Malformed(other),
        })?;
    if used != payload.len() {
        return Err(DecodeError::TrailingBytes {
            count: payload.len().saturating_sub(used),
        });
    }
    env.validate(limits)?;
    Ok(env)
}
