//! The rendered world: an axis-aligned room (floor, ceiling and four walls)
//! around every robot's trajectory, each surface with its own texture.
//!
//! Seen from inside, a box is convex: a ray from a camera in the room leaves it
//! through exactly one face, so there is no occlusion and a pixel's 3-D point is
//! that exit point.

use nalgebra::Vector3;

/// One of the six faces: the axis it is normal to, and which side of the box.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Face {
    /// 0 (x), 1 (y) or 2 (z).
    pub axis: usize,
    /// `true` for the face at the box's maximum along `axis`.
    pub upper: bool,
}

impl Face {
    /// Index 0..6 of the face: `2 * axis + upper`.
    pub fn index(self) -> usize {
        2 * self.axis + usize::from(self.upper)
    }
}

/// Where a ray leaves the room.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// The ray parameter: the point is `origin + s * dir`.
    pub s: f64,
    /// The face hit.
    pub face: Face,
    /// The point in the world frame, metres.
    pub point: Vector3<f64>,
}

/// An axis-aligned room, metres in the world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Room {
    /// Lowest corner.
    pub min: Vector3<f64>,
    /// Highest corner.
    pub max: Vector3<f64>,
}

impl Room {
    /// The room around `points` with `margin_m` of horizontal space to the walls,
    /// the floor `floor_below_m` below the lowest point and the ceiling
    /// `ceiling_above_m` above the highest. `None` without points.
    pub fn around(
        points: impl IntoIterator<Item = Vector3<f64>>,
        margin_m: f64,
        floor_below_m: f64,
        ceiling_above_m: f64,
    ) -> Option<Self> {
        let mut it = points.into_iter();
        let first = it.next()?;
        let (lo, hi) = it.fold((first, first), |(lo, hi), p| (lo.inf(&p), hi.sup(&p)));
        let grow_lo = Vector3::new(margin_m, margin_m, floor_below_m);
        let grow_hi = Vector3::new(margin_m, margin_m, ceiling_above_m);
        Some(Self {
            min: lo - grow_lo,
            max: hi + grow_hi,
        })
    }

    /// Whether `p` is strictly inside.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        (0..3).all(|i| p[i] > self.min[i] && p[i] < self.max[i])
    }

    /// Where the ray `origin + s * dir` (`s > 0`) from inside the room leaves it;
    /// `None` from outside or for a zero direction.
    pub fn exit(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Hit> {
        if !self.contains(origin) {
            return None;
        }
        let mut best: Option<(f64, Face)> = None;
        for axis in 0..3 {
            let d = dir[axis];
            if d == 0.0 || !d.is_finite() {
                continue;
            }
            let upper = d > 0.0;
            let bound = if upper {
                self.max[axis]
            } else {
                self.min[axis]
            };
            let s = (bound - origin[axis]) / d;
            if best.is_none_or(|(b, _)| s < b) {
                best = Some((s, Face { axis, upper }));
            }
        }
        let (s, face) = best?;
        let mut point = origin + dir * s;
        // Exactly on the face, whatever the rounding.
        point[face.axis] = if face.upper {
            self.max[face.axis]
        } else {
            self.min[face.axis]
        };
        Some(Hit { s, face, point })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_leave_through_the_face_they_point_at() {
        let room = Room::around(
            [Vector3::zeros(), Vector3::new(2.0, 2.0, 1.0)],
            1.0,
            1.0,
            2.0,
        )
        .expect("points");
        assert_eq!(room.min, Vector3::new(-1.0, -1.0, -1.0));
        assert_eq!(room.max, Vector3::new(3.0, 3.0, 3.0));
        let o = Vector3::new(0.0, 0.0, 0.0);
        let floor = room.exit(&o, &Vector3::new(0.1, 0.0, -1.0)).expect("hit");
        assert_eq!(
            floor.face,
            Face {
                axis: 2,
                upper: false
            }
        );
        assert!((floor.s - 1.0).abs() < 1e-12);
        assert!((floor.point - Vector3::new(0.1, 0.0, -1.0)).norm() < 1e-12);
        let wall = room.exit(&o, &Vector3::new(1.0, 0.2, 0.1)).expect("hit");
        assert_eq!(wall.face.index(), 1);
        assert!(room
            .exit(&Vector3::new(9.0, 0.0, 0.0), &Vector3::x())
            .is_none());
        assert!(room.exit(&o, &Vector3::zeros()).is_none());
    }
}
