//! 8-bit grayscale images, as cameras, the renderer and the image frontend pass
//! them around, and their PNG encoding (for datasets and logs).
//!
//! Pixel `(x, y)` is `data[y * width + x]`, `x` to the right and `y` down. Its
//! intensity is the camera's response at the continuous pixel coordinate
//! `(x, y)` (pixel centres at integer coordinates, as OpenCV and Kalibr
//! calibrations use them).

use std::io::Cursor;
use thiserror::Error;

/// Largest accepted image side (pixels): bounds memory on untrusted files.
pub const MAX_IMAGE_SIDE: u32 = 16_384;

/// Why an image could not be made, decoded or encoded.
#[derive(Debug, Error)]
pub enum ImageError {
    /// The buffer does not hold `width * height` bytes, or a side is zero or too big.
    #[error(
        "image of {width}x{height} pixels cannot hold {len} bytes (sides 1..={MAX_IMAGE_SIDE})"
    )]
    BadSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Bytes given.
        len: usize,
    },
    /// The PNG data is malformed.
    #[error("PNG decoding: {0}")]
    Decode(#[from] png::DecodingError),
    /// The PNG could not be written.
    #[error("PNG encoding: {0}")]
    Encode(#[from] png::EncodingError),
    /// The PNG has a pixel layout this reader does not handle.
    #[error("unsupported PNG pixel layout: {0}")]
    Unsupported(String),
}

/// An 8-bit grayscale image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GrayImage {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl GrayImage {
    /// An image from its row-major pixels; the length must be `width * height`.
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self, ImageError> {
        let ok_side = |s: u32| (1..=MAX_IMAGE_SIDE).contains(&s);
        if !ok_side(width) || !ok_side(height) || data.len() != width as usize * height as usize {
            return Err(ImageError::BadSize {
                width,
                height,
                len: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Row-major pixels.
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// Intensity at integer pixel `(x, y)`, `None` outside the image.
    pub fn get(&self, x: u32, y: u32) -> Option<u8> {
        (x < self.width && y < self.height)
            .then(|| self.data[y as usize * self.width as usize + x as usize])
    }

    /// Decodes a PNG: 8- or 16-bit gray (16-bit keeps its high byte, as TUM-VI's
    /// 16-bit images need), gray with alpha, RGB or RGBA (converted with the
    /// ITU-R BT.601 luma weights); palettes are expanded first.
    pub fn from_png(bytes: &[u8]) -> Result<Self, ImageError> {
        let mut decoder = png::Decoder::new(Cursor::new(bytes));
        decoder.set_transformations(png::Transformations::EXPAND);
        let mut reader = decoder.read_info()?;
        let (w, h) = {
            let info = reader.info();
            (info.width, info.height)
        };
        if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
            return Err(ImageError::BadSize {
                width: w,
                height: h,
                len: 0,
            });
        }
        let size = reader
            .output_buffer_size()
            .ok_or_else(|| ImageError::Unsupported("output size overflows".into()))?;
        let mut buf = vec![0u8; size];
        let frame = reader.next_frame(&mut buf)?;
        let (color, depth) = (frame.color_type, frame.bit_depth);
        let bytes_per_sample = match depth {
            png::BitDepth::Eight => 1,
            png::BitDepth::Sixteen => 2,
            other => return Err(ImageError::Unsupported(format!("bit depth {other:?}"))),
        };
        let channels = match color {
            png::ColorType::Grayscale => 1,
            png::ColorType::GrayscaleAlpha => 2,
            png::ColorType::Rgb => 3,
            png::ColorType::Rgba => 4,
            other => return Err(ImageError::Unsupported(format!("color type {other:?}"))),
        };
        let stride = frame.line_size;
        let pixel = bytes_per_sample * channels;
        let mut data = Vec::with_capacity(w as usize * h as usize);
        for row in buf.chunks(stride).take(h as usize) {
            for px in row.chunks_exact(pixel).take(w as usize) {
                // The high byte of each sample (big-endian in PNG).
                let s = |c: usize| f64::from(px[c * bytes_per_sample]);
                let v = match channels {
                    1 | 2 => s(0),
                    _ => 0.299 * s(0) + 0.587 * s(1) + 0.114 * s(2),
                };
                data.push(v.round().clamp(0.0, 255.0) as u8);
            }
        }
        Self::new(w, h, data)
    }

    /// Encodes as an 8-bit grayscale PNG (fast compression: logs are written
    /// while the robot runs).
    pub fn to_png(&self) -> Result<Vec<u8>, ImageError> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width, self.height);
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::Eight);
            enc.set_compression(png::Compression::Fast);
            let mut w = enc.write_header()?;
            w.write_image_data(&self.data)?;
            w.finish()?;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trip_keeps_every_pixel() {
        let data: Vec<u8> = (0..12 * 7).map(|i| (i * 37 % 256) as u8).collect();
        let img = GrayImage::new(12, 7, data).unwrap();
        let back = GrayImage::from_png(&img.to_png().unwrap()).unwrap();
        assert_eq!(back, img);
        assert_eq!(back.get(11, 6), Some(img.data()[83]));
        assert_eq!(back.get(12, 0), None);
    }

    #[test]
    fn wrong_sizes_and_garbage_are_errors() {
        assert!(GrayImage::new(0, 5, vec![]).is_err());
        assert!(GrayImage::new(3, 3, vec![0; 8]).is_err());
        assert!(GrayImage::from_png(b"not a png").is_err());
        let img = GrayImage::new(4, 4, vec![9; 16]).unwrap();
        let png = img.to_png().unwrap();
        assert!(GrayImage::from_png(&png[..png.len() / 2]).is_err());
    }
}
