//! 256-bit binary descriptors (ORB-like) and their Hamming distance.

use serde::{Deserialize, Serialize};

/// A 256-bit binary descriptor, as ORB produces; bit `i` is bit `i % 64` of word `i / 64`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub struct Descriptor(pub [u64; 4]);

impl Descriptor {
    /// Number of bits in a descriptor.
    pub const BITS: usize = 256;

    /// Hamming distance (number of differing bits), 0..=256.
    pub fn distance(&self, other: &Descriptor) -> u32 {
        self.0
            .iter()
            .zip(other.0.iter())
            .map(|(a, b)| (a ^ b).count_ones())
            .sum()
    }

    /// Value of bit `i` (0..256).
    pub fn bit(&self, i: usize) -> bool {
        (self.0[(i / 64) % 4] >> (i % 64)) & 1 == 1
    }

    /// Flips bit `i` (0..256).
    pub fn flip(&mut self, i: usize) {
        self.0[(i / 64) % 4] ^= 1 << (i % 64);
    }

    /// The 32 bytes, little-endian per word (the byte order OpenCV's ORB rows use
    /// when read as u64 words on little-endian machines).
    pub fn to_bytes(&self) -> [u8; 32] {
        let mut out = [0u8; 32];
        for (w, chunk) in self.0.iter().zip(out.chunks_exact_mut(8)) {
            chunk.copy_from_slice(&w.to_le_bytes());
        }
        out
    }

    /// Inverse of [`Descriptor::to_bytes`].
    pub fn from_bytes(bytes: &[u8; 32]) -> Self {
        let mut words = [0u64; 4];
        for (w, chunk) in words.iter_mut().zip(bytes.chunks_exact(8)) {
            let mut b = [0u8; 8];
            b.copy_from_slice(chunk);
            *w = u64::from_le_bytes(b);
        }
        Descriptor(words)
    }

    /// Lower-case hex of [`Descriptor::to_bytes`] (64 characters).
    pub fn to_hex(&self) -> String {
        self.to_bytes().iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Parses 64 hex characters; `None` if malformed.
    pub fn from_hex(s: &str) -> Option<Self> {
        let s = s.as_bytes();
        if s.len() != 64 {
            return None;
        }
        let mut bytes = [0u8; 32];
        for (i, b) in bytes.iter_mut().enumerate() {
            let hi = (s[2 * i] as char).to_digit(16)?;
            let lo = (s[2 * i + 1] as char).to_digit(16)?;
            *b = (hi * 16 + lo) as u8;
        }
        Some(Self::from_bytes(&bytes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_counts_flipped_bits() {
        let a = Descriptor([0xdead_beef, 1, 2, u64::MAX]);
        let mut b = a;
        for i in [0, 63, 64, 200, 255] {
            b.flip(i);
        }
        assert_eq!(a.distance(&b), 5);
        assert_eq!(a.distance(&a), 0);
        assert!(b.bit(255) != a.bit(255));
    }

    #[test]
    fn bytes_and_hex_round_trip() {
        let a = Descriptor([1, 0x0123_4567_89ab_cdef, 42, u64::MAX - 7]);
        assert_eq!(Descriptor::from_bytes(&a.to_bytes()), a);
        assert_eq!(Descriptor::from_hex(&a.to_hex()), Some(a));
        assert_eq!(Descriptor::from_hex("zz"), None);
    }
}
