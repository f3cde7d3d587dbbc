//! Conversions between our types and OpenCV's.

use common::image::GrayImage;
use nalgebra::Vector2;
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;

/// An owned 8-bit single-channel `Mat` with the image's pixels.
pub fn mat_of(image: &GrayImage) -> opencv::Result<Mat> {
    let rows = i32::try_from(image.height()).unwrap_or(i32::MAX);
    let cols = i32::try_from(image.width()).unwrap_or(i32::MAX);
    let view = Mat::new_rows_cols_with_data(rows, cols, image.data())?;
    view.try_clone()
}

/// OpenCV points of pixel coordinates.
pub fn points_of(uv: &[Vector2<f64>]) -> Vector<Point2f> {
    uv.iter()
        .map(|p| Point2f::new(p.x as f32, p.y as f32))
        .collect()
}

/// Pixel coordinates of OpenCV points.
pub fn pixels_of(points: &Vector<Point2f>) -> Vec<Vector2<f64>> {
    points
        .iter()
        .map(|p| Vector2::new(f64::from(p.x), f64::from(p.y)))
        .collect()
}
