//! The text format of descriptor sets: one image per line, each descriptor as 64
//! hex characters ([`Descriptor::to_hex`]), separated by whitespace. A blank line
//! is an image without descriptors.

use common::descriptor::Descriptor;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a descriptor file could not be read or written.
#[derive(Debug, Error)]
pub enum TextError {
    /// The file could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file could not be written.
    #[error("cannot write {}: {source}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A token is not a descriptor.
    #[error("{}:{line}: `{token}` is not a 64-hex-digit descriptor", path.display())]
    BadDescriptor {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The token (at most 80 characters of it).
        token: String,
    },
}

/// Parses the images of `text`; `path` only names the source in errors.
pub fn parse_images(text: &str, path: &Path) -> Result<Vec<Vec<Descriptor>>, TextError> {
    text.lines()
        .enumerate()
        .map(|(i, line)| {
            line.split_whitespace()
                .map(|tok| {
                    Descriptor::from_hex(tok).ok_or_else(|| TextError::BadDescriptor {
                        path: path.to_path_buf(),
                        line: i + 1,
                        token: tok.chars().take(80).collect(),
                    })
                })
                .collect()
        })
        .collect()
}

/// Reads a descriptor file.
pub fn read_images(path: &Path) -> Result<Vec<Vec<Descriptor>>, TextError> {
    let text = std::fs::read_to_string(path).map_err(|source| TextError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_images(&text, path)
}

/// Formats images, one line each.
pub fn format_images<I: AsRef<[Descriptor]>>(images: &[I]) -> String {
    let mut out = String::with_capacity(images.iter().map(|i| 65 * i.as_ref().len() + 1).sum());
    for image in images {
        for (j, d) in image.as_ref().iter().enumerate() {
            if j > 0 {
                out.push(' ');
            }
            out.push_str(&d.to_hex());
        }
        out.push('\n');
    }
    out
}

/// Writes a descriptor file.
pub fn write_images<I: AsRef<[Descriptor]>>(path: &Path, images: &[I]) -> Result<(), TextError> {
    std::fs::write(path, format_images(images)).map_err(|source| TextError::Write {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let images = vec![
            vec![Descriptor([1, 2, 3, 4]), Descriptor([u64::MAX, 0, 7, 9])],
            vec![],
            vec![Descriptor([5, 5, 5, 5])],
        ];
        let text = format_images(&images);
        assert_eq!(parse_images(&text, Path::new("x")).unwrap(), images);
        let err = parse_images("\nabc\n", Path::new("f.txt")).unwrap_err();
        assert!(err.to_string().contains("f.txt:2"), "{err}");
    }
}
