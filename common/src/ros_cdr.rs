//! ROS 2 sensor messages as they travel over Zenoh: `sensor_msgs/msg/Imu` and
//! `sensor_msgs/msg/Image` in CDR (OMG Common Data Representation, XCDR1), the
//! bytes that `zenoh-bridge-ros2dds` and `rmw_zenoh` put in a sample's payload.
//!
//! A payload starts with a 4-byte encapsulation header (`00 01`: little
//! endian, `00 00`: big endian, then two option bytes). Every primitive is
//! aligned to its own size, counted from the end of that header; a string is
//! a `u32` length that counts its closing NUL, then the bytes; a sequence is a
//! `u32` count, then the elements.
//!
//! The payloads come off the network: the decoder checks every length against
//! the bytes that are there before it allocates, bounds images by
//! [`MAX_IMAGE_SIDE`], and rejects non-finite IMU readings with the field that
//! was not finite.

use crate::image::{GrayImage, MAX_IMAGE_SIDE};
use crate::measurement::ImuSample;
use crate::trajectory::{StampedCovariance, StampedPose};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use thiserror::Error;

/// Why a payload is not the message it was taken for.
#[derive(Debug, Error, PartialEq)]
pub enum CdrError {
    /// Fewer bytes than the message needs.
    #[error("payload ends at byte {len}, {needed} more needed for {what}")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// The payload's length.
        len: usize,
        /// Bytes missing.
        needed: usize,
    },
    /// The encapsulation header names a representation this decoder does not read.
    #[error("encapsulation {0:#06x} is not plain CDR (0x0000 big endian, 0x0001 little endian)")]
    Encapsulation(u16),
    /// A string is not NUL-terminated UTF-8.
    #[error("{0} is not a NUL-terminated UTF-8 string")]
    BadString(&'static str),
    /// A reading is NaN or infinite.
    #[error("{0} is not finite")]
    NotFinite(&'static str),
    /// A quaternion is not of unit norm.
    #[error("{0} is not a unit quaternion")]
    NotUnit(&'static str),
    /// The stamp is negative or its nanoseconds exceed a second.
    #[error("stamp {sec} s {nanosec} ns is not a time")]
    BadStamp {
        /// Seconds.
        sec: i32,
        /// Nanoseconds.
        nanosec: u32,
    },
    /// The image's fields disagree or exceed the bounds.
    #[error("image {width}x{height}, step {step}, {len} data bytes, encoding {encoding:?}: {why}")]
    BadImage {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
        /// Row length, bytes.
        step: u32,
        /// Data bytes.
        len: usize,
        /// Pixel encoding.
        encoding: String,
        /// What is wrong.
        why: &'static str,
    },
    /// A pixel encoding this decoder does not turn into gray.
    #[error(
        "image encoding {0:?} is not one of mono8, 8UC1, mono16, 16UC1, rgb8, bgr8, rgba8, bgra8"
    )]
    Encoding(String),
}

/// `std_msgs/Header`: the stamp and the frame id.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// Seconds since the epoch of the sender's clock.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
    /// The sensor's frame.
    pub frame_id: String,
}

impl Header {
    /// The stamp in seconds.
    pub fn t_s(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }

    /// The header of time `t_s` (seconds, rounded to the nanosecond). A time
    /// outside ROS's `int32` seconds is held at its bounds instead of wrapping.
    pub fn at(t_s: f64, frame_id: &str) -> Self {
        let ns = (t_s * 1e9).round() as i64;
        let sec = ns.div_euclid(1_000_000_000);
        Self {
            sec: sec.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
            nanosec: ns.rem_euclid(1_000_000_000) as u32,
            frame_id: frame_id.to_owned(),
        }
    }
}

/// The parts of `sensor_msgs/Imu` an estimator reads.
#[derive(Clone, Debug, PartialEq)]
pub struct RosImu {
    /// Stamp and frame.
    pub header: Header,
    /// Angular velocity, rad/s.
    pub angular_velocity: Vector3<f64>,
    /// Linear acceleration (specific force), m/s².
    pub linear_acceleration: Vector3<f64>,
}

impl RosImu {
    /// The sample at the header's time.
    pub fn sample(&self) -> ImuSample {
        ImuSample {
            t: self.header.t_s(),
            gyro: self.angular_velocity,
            accel: self.linear_acceleration,
        }
    }
}

/// A `sensor_msgs/Image` turned into gray.
#[derive(Clone, Debug, PartialEq)]
pub struct RosImage {
    /// Stamp and frame.
    pub header: Header,
    /// The pixels (color averaged, 16-bit by the high byte).
    pub image: GrayImage,
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> Reader<'a> {
    fn new(payload: &'a [u8]) -> Result<Self, CdrError> {
        // Lazily: `4 - len` underflows for every payload that has a header
        // (a panic in debug builds).
        let head = payload.get(..4).ok_or_else(|| CdrError::Truncated {
            what: "the encapsulation header",
            len: payload.len(),
            needed: 4 - payload.len(),
        })?;
        let little = match u16::from_be_bytes([head[0], head[1]]) {
            0x0000 => false,
            0x0001 => true,
            other => return Err(CdrError::Encapsulation(other)),
        };
        Ok(Self {
            buf: &payload[4..],
            pos: 0,
            little,
        })
    }

    fn take(&mut self, n: usize, align: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        let start = self.pos.next_multiple_of(align);
        let end = start.saturating_add(n);
        if end > self.buf.len() {
            return Err(CdrError::Truncated {
                what,
                len: self.buf.len() + 4,
                needed: end.saturating_sub(self.buf.len()),
            });
        }
        self.pos = end;
        Ok(&self.buf[start..end])
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CdrError> {
        let b = self.take(N, N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(b);
        if !self.little {
            a.reverse();
        }
        Ok(a)
    }

    fn u8(&mut self, what: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(1, 1, what)?[0])
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, CdrError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    fn i32(&mut self, what: &'static str) -> Result<i32, CdrError> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }

    fn f64(&mut self, what: &'static str) -> Result<f64, CdrError> {
        let v = f64::from_le_bytes(self.array(what)?);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(CdrError::NotFinite(what))
        }
    }

    /// Doubles whose value is not read (covariances, orientation): any bits.
    fn skip_f64s(&mut self, n: usize, what: &'static str) -> Result<(), CdrError> {
        self.take(8 * n, 8, what).map(|_| ())
    }

    fn vector3(&mut self, what: &'static str) -> Result<Vector3<f64>, CdrError> {
        Ok(Vector3::new(
            self.f64(what)?,
            self.f64(what)?,
            self.f64(what)?,
        ))
    }

    fn string(&mut self, what: &'static str) -> Result<String, CdrError> {
        let len = self.u32(what)? as usize;
        let bytes = self.take(len, 1, what)?;
        match bytes.split_last() {
            Some((0, text)) => std::str::from_utf8(text)
                .map(str::to_owned)
                .map_err(|_| CdrError::BadString(what)),
            _ => Err(CdrError::BadString(what)),
        }
    }

    fn header(&mut self) -> Result<Header, CdrError> {
        let sec = self.i32("header.stamp.sec")?;
        let nanosec = self.u32("header.stamp.nanosec")?;
        if sec < 0 || nanosec >= 1_000_000_000 {
            return Err(CdrError::BadStamp { sec, nanosec });
        }
        let frame_id = self.string("header.frame_id")?;
        Ok(Header {
            sec,
            nanosec,
            frame_id,
        })
    }
}

/// Decodes a `sensor_msgs/msg/Imu` payload.
pub fn decode_imu(payload: &[u8]) -> Result<RosImu, CdrError> {
    let mut r = Reader::new(payload)?;
    let header = r.header()?;
    r.skip_f64s(4, "orientation")?;
    r.skip_f64s(9, "orientation_covariance")?;
    let angular_velocity = r.vector3("angular_velocity")?;
    r.skip_f64s(9, "angular_velocity_covariance")?;
    let linear_acceleration = r.vector3("linear_acceleration")?;
    r.skip_f64s(9, "linear_acceleration_covariance")?;
    Ok(RosImu {
        header,
        angular_velocity,
        linear_acceleration,
    })
}

/// Decodes a `sensor_msgs/msg/Image` payload into gray. Color is averaged
/// over its channels, 16-bit pixels are read by their high byte; rows may be
/// padded (`step` beyond the pixels).
pub fn decode_image(payload: &[u8]) -> Result<RosImage, CdrError> {
    let mut r = Reader::new(payload)?;
    let header = r.header()?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    let encoding = r.string("encoding")?;
    let big_endian = r.u8("is_bigendian")? != 0;
    let step = r.u32("step")?;
    let len = r.u32("data")? as usize;
    let bad = |why| CdrError::BadImage {
        width,
        height,
        step,
        len,
        encoding: encoding.clone(),
        why,
    };
    if !(1..=MAX_IMAGE_SIDE).contains(&width) || !(1..=MAX_IMAGE_SIDE).contains(&height) {
        return Err(bad("sides must be 1 to 16384 pixels"));
    }
    let (channels, bytes) = match encoding.as_str() {
        "mono8" | "8UC1" => (1usize, 1usize),
        "mono16" | "16UC1" => (1, 2),
        "rgb8" | "bgr8" | "8UC3" => (3, 1),
        "rgba8" | "bgra8" | "8UC4" => (4, 1),
        _ => return Err(CdrError::Encoding(encoding)),
    };
    let row = width as usize * channels * bytes;
    if (step as usize) < row {
        return Err(bad("step is shorter than a row"));
    }
    if len != step as usize * height as usize {
        return Err(bad("data is not step x height bytes"));
    }
    let data = r.take(len, 1, "data")?;
    let mut gray = Vec::with_capacity(width as usize * height as usize);
    for y in 0..height as usize {
        let line = &data[y * step as usize..][..row];
        match (channels, bytes) {
            (1, 1) => gray.extend_from_slice(line),
            (1, _) => gray.extend(
                line.chunks_exact(2)
                    .map(|p| if big_endian { p[0] } else { p[1] }),
            ),
            (c, _) => gray.extend(line.chunks_exact(c).map(|p| {
                // Equal weights: which channel is red does not matter then.
                let sum: u32 = p[..3].iter().map(|&v| u32::from(v)).sum();
                ((sum + 1) / 3) as u8
            })),
        }
    }
    let image =
        GrayImage::new(width, height, gray).map_err(|_| bad("pixels do not fill the image"))?;
    Ok(RosImage { header, image })
}

/// Writes CDR, little endian: what a ROS 2 publisher on x86 or ARM sends.
#[derive(Default)]
struct Writer {
    buf: Vec<u8>,
}

impl Writer {
    fn new() -> Self {
        Self {
            buf: vec![0x00, 0x01, 0x00, 0x00],
        }
    }

    fn align(&mut self, n: usize) {
        let body = self.buf.len() - 4;
        self.buf.resize(4 + body.next_multiple_of(n), 0);
    }

    fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    fn header(&mut self, h: &Header) {
        self.i32(h.sec);
        self.u32(h.nanosec);
        self.string(&h.frame_id);
    }
}

/// Encodes a `sensor_msgs/msg/Imu` with no orientation (its covariance's
/// first element -1, as REP 145 asks) and unknown covariances (zeros).
pub fn encode_imu(header: &Header, s: &ImuSample) -> Vec<u8> {
    let mut w = Writer::new();
    w.header(header);
    for v in [0.0, 0.0, 0.0, 1.0] {
        w.f64(v);
    }
    for i in 0..9 {
        w.f64(if i == 0 { -1.0 } else { 0.0 });
    }
    for v in s.gyro.iter() {
        w.f64(*v);
    }
    (0..9).for_each(|_| w.f64(0.0));
    for v in s.accel.iter() {
        w.f64(*v);
    }
    (0..9).for_each(|_| w.f64(0.0));
    w.buf
}

/// Encodes a `sensor_msgs/msg/Image` of encoding `mono8`.
pub fn encode_mono8(header: &Header, image: &GrayImage) -> Vec<u8> {
    let mut w = Writer::new();
    w.header(header);
    w.u32(image.height());
    w.u32(image.width());
    w.string("mono8");
    w.buf.push(0);
    w.u32(image.width());
    w.u32(image.data().len() as u32);
    w.buf.extend_from_slice(image.data());
    w.buf
}

/// `geometry_msgs/PoseWithCovarianceStamped`: where the robot is and how
/// sure it is, as ROS 2 localization nodes publish it.
#[derive(Clone, Debug, PartialEq)]
pub struct RosPose {
    /// Stamp and the world's frame id.
    pub header: Header,
    /// The pose: `R_ItoG`, `p_IinG`.
    pub pose: StampedPose,
    /// Covariance of (x, y, z, rotation about the world's x, y, z), row-major.
    pub covariance: [f64; 36],
}

/// The 6x6 covariance ROS puts beside a pose: position, then rotation about
/// the fixed (world) axes. Ours perturbs the rotation in the body frame
/// (`R = R̂ Exp(δθ)`), so the world's rotation error is `R̂ δθ`; position and
/// orientation are marginals, so their cross terms are left zero.
pub fn ros_pose_covariance(pose: &StampedPose, cov: &StampedCovariance) -> [f64; 36] {
    let ori_world = pose.rot * cov.ori * pose.rot.transpose();
    let mut out = [0.0; 36];
    for r in 0..3 {
        for c in 0..3 {
            out[6 * r + c] = cov.pos[(r, c)];
            out[6 * (r + 3) + c + 3] = ori_world[(r, c)];
        }
    }
    out
}

/// Encodes a `geometry_msgs/msg/PoseWithCovarianceStamped`.
pub fn encode_pose(header: &Header, pose: &StampedPose, covariance: &[f64; 36]) -> Vec<u8> {
    let mut w = Writer::new();
    w.header(header);
    w.pose_with_covariance(pose, covariance);
    w.buf
}

/// Decodes a `geometry_msgs/msg/PoseWithCovarianceStamped`.
pub fn decode_pose(payload: &[u8]) -> Result<RosPose, CdrError> {
    let mut r = Reader::new(payload)?;
    let header = r.header()?;
    let (pose, covariance) = r.pose_with_covariance(header.t_s())?;
    Ok(RosPose {
        pose,
        header,
        covariance,
    })
}

/// `geometry_msgs/TwistWithCovariance`: a velocity and an angular rate, in
/// the frame the message names (an odometry's `child_frame_id`).
#[derive(Clone, Debug, PartialEq)]
pub struct RosTwist {
    /// Linear velocity, m/s.
    pub linear: Vector3<f64>,
    /// Angular rate, rad/s.
    pub angular: Vector3<f64>,
    /// Covariance of (vx, vy, vz, wx, wy, wz), row-major.
    pub covariance: [f64; 36],
}

/// `nav_msgs/Odometry`: the pose in the header's frame, the twist in the
/// body's (`child_frame_id`), as a controller or `robot_localization` takes
/// it.
#[derive(Clone, Debug, PartialEq)]
pub struct RosOdometry {
    /// Stamp and the world's frame id.
    pub header: Header,
    /// The body's frame id.
    pub child_frame_id: String,
    /// The pose: `R_ItoG`, `p_IinG`.
    pub pose: StampedPose,
    /// Covariance of the pose, as in [`RosPose::covariance`].
    pub pose_covariance: [f64; 36],
    /// The twist, in the body's axes.
    pub twist: RosTwist,
}

/// Encodes a `nav_msgs/msg/Odometry`.
pub fn encode_odometry(
    header: &Header,
    child_frame_id: &str,
    pose: &StampedPose,
    pose_covariance: &[f64; 36],
    twist: &RosTwist,
) -> Vec<u8> {
    let mut w = Writer::new();
    w.header(header);
    w.string(child_frame_id);
    w.pose_with_covariance(pose, pose_covariance);
    for v in twist.linear.iter().chain(twist.angular.iter()) {
        w.f64(*v);
    }
    for v in &twist.covariance {
        w.f64(*v);
    }
    w.buf
}

/// Decodes a `nav_msgs/msg/Odometry`.
pub fn decode_odometry(payload: &[u8]) -> Result<RosOdometry, CdrError> {
    let mut r = Reader::new(payload)?;
    let header = r.header()?;
    let child_frame_id = r.string("child_frame_id")?;
    let (pose, pose_covariance) = r.pose_with_covariance(header.t_s())?;
    let linear = r.vector3("twist.linear")?;
    let angular = r.vector3("twist.angular")?;
    let mut covariance = [0.0; 36];
    for v in &mut covariance {
        *v = r.f64("twist.covariance")?;
    }
    Ok(RosOdometry {
        header,
        child_frame_id,
        pose,
        pose_covariance,
        twist: RosTwist {
            linear,
            angular,
            covariance,
        },
    })
}

impl Writer {
    /// A `geometry_msgs/PoseWithCovariance`.
    fn pose_with_covariance(&mut self, pose: &StampedPose, covariance: &[f64; 36]) {
        for v in pose.pos.iter() {
            self.f64(*v);
        }
        let q = UnitQuaternion::from_matrix(&pose.rot);
        for v in [q.i, q.j, q.k, q.w] {
            self.f64(v);
        }
        for v in covariance {
            self.f64(*v);
        }
    }
}

impl Reader<'_> {
    /// A `geometry_msgs/PoseWithCovariance`, stamped `t_s`; the orientation
    /// must be a unit quaternion.
    fn pose_with_covariance(&mut self, t_s: f64) -> Result<(StampedPose, [f64; 36]), CdrError> {
        let pos = self.vector3("pose.position")?;
        let (x, y, z, w) = (
            self.f64("pose.orientation")?,
            self.f64("pose.orientation")?,
            self.f64("pose.orientation")?,
            self.f64("pose.orientation")?,
        );
        let q = Quaternion::new(w, x, y, z);
        if (q.norm() - 1.0).abs() > 1e-6 {
            return Err(CdrError::NotUnit("pose.orientation"));
        }
        let mut covariance = [0.0; 36];
        for v in &mut covariance {
            *v = self.f64("pose.covariance")?;
        }
        let pose = StampedPose {
            t: t_s,
            rot: UnitQuaternion::from_quaternion(q)
                .to_rotation_matrix()
                .into_inner(),
            pos,
        };
        Ok((pose, covariance))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> ImuSample {
        ImuSample {
            t: 1_403_715_273.262_143,
            gyro: Vector3::new(-0.0991, 0.1417, 0.0251),
            accel: Vector3::new(8.1476, -0.3749, -2.4433),
        }
    }

    /// The bytes of one message laid out by hand, as a ROS 2 node on a
    /// little-endian machine sends them: header, then the doubles aligned to
    /// 8 bytes from the end of the encapsulation header.
    #[test]
    fn an_imu_message_laid_out_by_hand_decodes() {
        let mut b = vec![0x00, 0x01, 0x00, 0x00];
        b.extend_from_slice(&7i32.to_le_bytes());
        b.extend_from_slice(&250_000_000u32.to_le_bytes());
        b.extend_from_slice(&5u32.to_le_bytes());
        b.extend_from_slice(b"imu0\0");
        // 17 body bytes so far: the orientation starts at body offset 24.
        b.extend_from_slice(&[0; 7]);
        let doubles: Vec<f64> = [0.0; 4]
            .into_iter()
            .chain([0.0; 9])
            .chain([0.1, 0.2, 0.3])
            .chain([0.0; 9])
            .chain([1.0, 2.0, 9.81])
            .chain([0.0; 9])
            .collect();
        for d in doubles {
            b.extend_from_slice(&d.to_le_bytes());
        }
        let m = decode_imu(&b).expect("decodes");
        assert_eq!(m.header.frame_id, "imu0");
        assert!((m.header.t_s() - 7.25).abs() < 1e-12);
        assert_eq!(m.angular_velocity, Vector3::new(0.1, 0.2, 0.3));
        assert_eq!(m.linear_acceleration, Vector3::new(1.0, 2.0, 9.81));
    }

    #[test]
    fn imu_round_trips_to_the_nanosecond() {
        let s = sample();
        let h = Header::at(s.t, "imu4");
        let m = decode_imu(&encode_imu(&h, &s)).expect("decodes");
        assert_eq!(m.header, h);
        assert!((m.sample().t - s.t).abs() < 1e-6);
        assert_eq!(m.sample().gyro, s.gyro);
        assert_eq!(m.sample().accel, s.accel);
    }

    #[test]
    fn big_endian_payloads_decode_too() {
        let mut b = vec![0x00, 0x00, 0x00, 0x00];
        b.extend_from_slice(&3i32.to_be_bytes());
        b.extend_from_slice(&0u32.to_be_bytes());
        b.extend_from_slice(&1u32.to_be_bytes());
        b.push(0);
        // 13 body bytes: the orientation starts at body offset 16.
        b.extend_from_slice(&[0, 0, 0]);
        for i in 0..42 {
            let v = if (13..16).contains(&i) { 0.5 } else { 0.0 };
            b.extend_from_slice(&f64::to_be_bytes(v));
        }
        let m = decode_imu(&b).expect("decodes");
        assert_eq!(m.header.sec, 3);
        assert_eq!(m.angular_velocity, Vector3::new(0.5, 0.5, 0.5));
    }

    #[test]
    fn every_truncation_of_an_imu_message_is_an_error_not_a_panic() {
        let b = encode_imu(&Header::at(1.0, "imu0"), &sample());
        for n in 0..b.len() {
            assert!(decode_imu(&b[..n]).is_err(), "{n} bytes");
        }
    }

    #[test]
    fn a_nan_reading_is_named() {
        let mut s = sample();
        s.accel.y = f64::NAN;
        let err = decode_imu(&encode_imu(&Header::at(1.0, "imu0"), &s)).unwrap_err();
        assert_eq!(err, CdrError::NotFinite("linear_acceleration"));
    }

    #[test]
    fn other_encapsulations_and_bad_stamps_are_refused() {
        let mut b = encode_imu(&Header::at(1.0, "imu0"), &sample());
        b[1] = 0x03; // PL_CDR_LE: parameter lists are not read.
        assert_eq!(decode_imu(&b).unwrap_err(), CdrError::Encapsulation(3));
        let h = Header {
            sec: 1,
            nanosec: 1_000_000_000,
            frame_id: String::new(),
        };
        assert!(matches!(
            decode_imu(&encode_imu(&h, &sample())),
            Err(CdrError::BadStamp { .. })
        ));
    }

    /// The pose round-trips, and the rotation's covariance is turned into
    /// the world's axes: a body-frame yaw uncertainty of a robot pitched by
    /// 90 degrees is an uncertainty about the world's x axis.
    #[test]
    fn a_pose_round_trips_with_its_covariance_in_world_axes() {
        let rot = nalgebra::Rotation3::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0)
            .into_inner();
        let pose = StampedPose {
            t: 100.25,
            rot,
            pos: Vector3::new(1.0, -2.0, 0.5),
        };
        let cov = StampedCovariance {
            t: 100.25,
            ori: nalgebra::Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, 4e-4)),
            pos: nalgebra::Matrix3::from_diagonal(&Vector3::new(1e-2, 2e-2, 3e-2)),
        };
        let c = ros_pose_covariance(&pose, &cov);
        assert_eq!([c[0], c[7], c[14]], [1e-2, 2e-2, 3e-2]);
        // Body z after a 90-degree pitch is the world's -x: variance on rx.
        assert!((c[21] - 4e-4).abs() < 1e-12 && c[28].abs() < 1e-12 && c[35].abs() < 1e-12);
        let m = decode_pose(&encode_pose(&Header::at(pose.t, "world"), &pose, &c)).expect("pose");
        assert_eq!(m.header.frame_id, "world");
        assert!((m.pose.rot - rot).norm() < 1e-12 && m.pose.pos == pose.pos);
        assert_eq!(m.covariance, c);
    }

    /// An odometry message round-trips, and every truncation of it is an
    /// error, not a panic.
    #[test]
    fn an_odometry_round_trips_with_its_twist() {
        let pose = StampedPose {
            t: 7.5,
            rot: nalgebra::Rotation3::from_euler_angles(0.1, -0.4, 2.0).into_inner(),
            pos: Vector3::new(3.0, 1.0, -0.5),
        };
        let mut pose_cov = [0.0; 36];
        let mut twist_cov = [0.0; 36];
        for k in 0..36 {
            pose_cov[k] = k as f64 * 1e-3;
            twist_cov[k] = -(k as f64) * 1e-4;
        }
        let twist = RosTwist {
            linear: Vector3::new(0.5, -0.1, 0.02),
            angular: Vector3::new(0.01, 0.2, -0.3),
            covariance: twist_cov,
        };
        let bytes = encode_odometry(
            &Header::at(7.5, "fleet_world"),
            "imu",
            &pose,
            &pose_cov,
            &twist,
        );
        let m = decode_odometry(&bytes).expect("odometry");
        assert_eq!(m.header.frame_id, "fleet_world");
        assert_eq!(m.child_frame_id, "imu");
        assert!((m.pose.rot - pose.rot).norm() < 1e-12 && m.pose.pos == pose.pos);
        assert_eq!(m.pose.t, 7.5);
        assert_eq!(m.pose_covariance, pose_cov);
        assert_eq!(m.twist, twist);
        for n in 0..bytes.len() {
            assert!(decode_odometry(&bytes[..n]).is_err(), "{n} bytes decoded");
        }
    }

    #[test]
    fn stamps_beyond_int32_seconds_are_held_and_a_non_unit_orientation_is_named() {
        assert_eq!(Header::at(1e12, "").sec, i32::MAX);
        assert_eq!(Header::at(-1e12, "").sec, i32::MIN);
        let pose = StampedPose {
            t: 1.0,
            rot: nalgebra::Matrix3::identity(),
            pos: Vector3::zeros(),
        };
        let mut b = encode_pose(&Header::at(1.0, "world"), &pose, &[0.0; 36]);
        // The quaternion's w (the fourth double after the position) set to 2.
        let w_at = b.len() - 36 * 8 - 8;
        b[w_at..w_at + 8].copy_from_slice(&2f64.to_le_bytes());
        assert_eq!(
            decode_pose(&b).unwrap_err(),
            CdrError::NotUnit("pose.orientation")
        );
    }

    #[test]
    fn a_mono8_image_round_trips() {
        let px: Vec<u8> = (0..12u8).collect();
        let img = GrayImage::new(4, 3, px).expect("image");
        let h = Header::at(12.5, "cam0");
        let m = decode_image(&encode_mono8(&h, &img)).expect("decodes");
        assert_eq!(m.header, h);
        assert_eq!(m.image, img);
    }

    /// Builds an image payload with any fields, to test the checks.
    fn image_payload(width: u32, height: u32, enc: &str, step: u32, data: &[u8]) -> Vec<u8> {
        let mut w = Writer::new();
        w.header(&Header::at(1.0, "cam0"));
        w.u32(height);
        w.u32(width);
        w.string(enc);
        w.buf.push(0);
        w.u32(step);
        w.u32(data.len() as u32);
        w.buf.extend_from_slice(data);
        w.buf
    }

    #[test]
    fn color_padded_rows_and_16_bit_images_become_gray() {
        // 2x2 bgr8 with one padding byte per row.
        let data = [30, 60, 90, 0, 0, 0, 9, 255, 255, 255, 3, 3, 3, 9];
        let m = decode_image(&image_payload(2, 2, "bgr8", 7, &data)).expect("decodes");
        assert_eq!(m.image.data(), &[60, 0, 255, 3]);
        // mono16, little endian: the high byte.
        let data = [0x34, 0x12, 0xff, 0xab];
        let m = decode_image(&image_payload(2, 1, "mono16", 4, &data)).expect("decodes");
        assert_eq!(m.image.data(), &[0x12, 0xab]);
    }

    #[test]
    fn inconsistent_or_huge_images_are_refused_before_allocating() {
        // Claims 16384x16384 with 4 bytes: refused on the length check.
        let e = decode_image(&image_payload(16_384, 16_384, "mono8", 16_384, &[0; 4])).unwrap_err();
        assert!(matches!(e, CdrError::BadImage { .. }), "{e}");
        let e = decode_image(&image_payload(20_000, 1, "mono8", 20_000, &[0; 4])).unwrap_err();
        assert!(matches!(e, CdrError::BadImage { .. }), "{e}");
        let e = decode_image(&image_payload(4, 1, "mono8", 3, &[0; 3])).unwrap_err();
        assert!(matches!(e, CdrError::BadImage { .. }), "{e}");
        let e = decode_image(&image_payload(1, 1, "yuv422", 2, &[0; 2])).unwrap_err();
        assert_eq!(e, CdrError::Encoding("yuv422".into()));
        // The data count says more than is there.
        let mut b = image_payload(2, 2, "mono8", 2, &[1, 2, 3, 4]);
        b.truncate(b.len() - 1);
        assert!(matches!(decode_image(&b), Err(CdrError::Truncated { .. })));
    }
}
