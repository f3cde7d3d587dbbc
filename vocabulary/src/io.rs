//! Vocabulary files: an 8-byte magic, the format version (`u32`, little-endian),
//! then the vocabulary in bincode (standard configuration).
//!
//! Reading is bounded and defensive: files above [`MAX_FILE_BYTES`] are refused
//! before being read, bincode decodes under the same byte limit, trailing bytes
//! and unknown versions are errors, and the decoded vocabulary is validated
//! ([`Vocabulary::validate`]: child indices in range, one tree, `k` and `L` sane,
//! finite weights) before it is returned. A corrupt file gives an error naming
//! the file, never a panic.

use crate::vocabulary::{InvalidVocabulary, Vocabulary};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The first bytes of every vocabulary file.
pub const MAGIC: [u8; 8] = *b"FVBOWVOC";
/// The format version written by this crate (the only one it reads).
pub const FORMAT_VERSION: u32 = 1;
/// Largest vocabulary file accepted, in bytes (1 GiB).
pub const MAX_FILE_BYTES: usize = 1 << 30;

const HEADER_LEN: usize = MAGIC.len() + 4;

fn config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_FILE_BYTES>()
}

/// Why bytes are not a vocabulary.
#[derive(Debug, Error)]
pub enum FormatError {
    /// Shorter than the header.
    #[error("too short for a vocabulary header ({0} bytes)")]
    Truncated(usize),
    /// The magic does not match.
    #[error("not a vocabulary file (bad magic)")]
    BadMagic,
    /// A version this crate does not read.
    #[error("unsupported format version {found} (this build reads version {supported})")]
    UnsupportedVersion {
        /// The file's version.
        found: u32,
        /// The version this build reads.
        supported: u32,
    },
    /// Larger than [`MAX_FILE_BYTES`].
    #[error("{len} bytes exceed the limit of {limit} bytes")]
    TooLarge {
        /// Its size.
        len: u64,
        /// The limit.
        limit: usize,
    },
    /// Bytes left after the vocabulary.
    #[error("{0} trailing bytes after the vocabulary")]
    TrailingBytes(usize),
    /// bincode could not decode the payload.
    #[error("cannot decode: {0}")]
    Decode(#[from] bincode::error::DecodeError),
    /// bincode could not encode the vocabulary.
    #[error("cannot encode: {0}")]
    Encode(#[from] bincode::error::EncodeError),
    /// The payload decoded but breaks an invariant.
    #[error(transparent)]
    Invalid(#[from] InvalidVocabulary),
}

/// Why a vocabulary file could not be read or written; every variant names the
/// file.
#[derive(Debug, Error)]
pub enum VocabIoError {
    /// Reading failed.
    #[error("cannot read vocabulary file {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Writing failed.
    #[error("cannot write vocabulary file {}: {source}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The contents are not a valid vocabulary (or could not be encoded).
    #[error("vocabulary file {}: {source}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: FormatError,
    },
}

impl Vocabulary {
    /// The file contents: header and bincode payload.
    pub fn to_bytes(&self) -> Result<Vec<u8>, FormatError> {
        let mut out = Vec::with_capacity(HEADER_LEN);
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        let payload = bincode::serde::encode_to_vec(self, config())?;
        out.extend_from_slice(&payload);
        Ok(out)
    }

    /// Parses file contents written by [`Vocabulary::to_bytes`], validating them.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, FormatError> {
        if bytes.len() > MAX_FILE_BYTES {
            return Err(FormatError::TooLarge {
                len: bytes.len() as u64,
                limit: MAX_FILE_BYTES,
            });
        }
        let (Some(magic), Some(version)) =
            (bytes.get(..MAGIC.len()), bytes.get(MAGIC.len()..HEADER_LEN))
        else {
            return Err(FormatError::Truncated(bytes.len()));
        };
        if magic != MAGIC {
            return Err(FormatError::BadMagic);
        }
        let mut v = [0u8; 4];
        v.copy_from_slice(version);
        let found = u32::from_le_bytes(v);
        if found != FORMAT_VERSION {
            return Err(FormatError::UnsupportedVersion {
                found,
                supported: FORMAT_VERSION,
            });
        }
        let payload = &bytes[HEADER_LEN..];
        let (vocab, used): (Vocabulary, usize) =
            bincode::serde::decode_from_slice(payload, config())?;
        if used != payload.len() {
            return Err(FormatError::TrailingBytes(payload.len() - used));
        }
        vocab.validate()?;
        Ok(vocab)
    }

    /// Writes the vocabulary to `path` (through a temporary file in the same
    /// directory, renamed into place).
    pub fn save(&self, path: &Path) -> Result<(), VocabIoError> {
        let bytes = self.to_bytes().map_err(|source| VocabIoError::Format {
            path: path.to_path_buf(),
            source,
        })?;
        let write_err = |source| VocabIoError::Write {
            path: path.to_path_buf(),
            source,
        };
        let mut tmp_name = path.file_name().unwrap_or_default().to_os_string();
        tmp_name.push(".tmp");
        let tmp = path.with_file_name(tmp_name);
        let mut f = std::fs::File::create(&tmp).map_err(write_err)?;
        f.write_all(&bytes).map_err(write_err)?;
        f.sync_all().map_err(write_err)?;
        drop(f);
        std::fs::rename(&tmp, path).map_err(write_err)
    }

    /// Reads and validates a vocabulary file.
    pub fn load(path: &Path) -> Result<Self, VocabIoError> {
        let read_err = |source| VocabIoError::Read {
            path: path.to_path_buf(),
            source,
        };
        let format_err = |source| VocabIoError::Format {
            path: path.to_path_buf(),
            source,
        };
        let f = std::fs::File::open(path).map_err(read_err)?;
        let len = f.metadata().map_err(read_err)?.len();
        if len > MAX_FILE_BYTES as u64 {
            return Err(format_err(FormatError::TooLarge {
                len,
                limit: MAX_FILE_BYTES,
            }));
        }
        let mut bytes = Vec::with_capacity(len as usize);
        f.take(MAX_FILE_BYTES as u64 + 1)
            .read_to_end(&mut bytes)
            .map_err(read_err)?;
        Self::from_bytes(&bytes).map_err(format_err)
    }
}
