//! Bad input is rejected with a reason, never a panic, and changes nothing.
//!
//! A robot stands still and level (identity orientation): IMU at 400 Hz reads no
//! rotation and gravity's reaction, frames at 10 Hz see a handful of features at
//! fixed pixels. Each case feeds one bad input to one estimator and not to a twin
//! fed the same valid stream; afterwards both must accept the same valid input and
//! produce bit-identical estimates.

use agent::estimator::{
    Estimator, EstimatorOptions, FrameError, FrameOutput, InitialState, InputError,
};
use common::calibration::CameraCalibration;
use common::conventions::GRAVITY_MPS2;
use common::descriptor::Descriptor;
use common::measurement::{FeatureFrame, FeatureObservation, ImuSample};
use nalgebra::{Matrix3, Vector2, Vector3};

const IMU_HZ: u32 = 400;
/// IMU samples per camera frame (10 Hz).
const IMU_PER_FRAME: u32 = 40;

/// Fixed pixels inside the 752x480 EuRoC image, ids 1..=8.
const PIXELS: [(f64, f64); 8] = [
    (100.0, 80.0),
    (650.0, 90.0),
    (376.0, 240.0),
    (120.0, 400.0),
    (600.0, 410.0),
    (250.0, 160.0),
    (500.0, 320.0),
    (380.0, 60.0),
];

fn imu_at(t: f64) -> ImuSample {
    ImuSample {
        t,
        gyro: Vector3::zeros(),
        accel: Vector3::new(0.0, 0.0, GRAVITY_MPS2),
    }
}

fn observation(id: u64, u: f64, v: f64) -> FeatureObservation {
    FeatureObservation {
        id,
        uv: Vector2::new(u, v),
        descriptor: Descriptor::default(),
    }
}

fn frame_with(t: f64, features: Vec<FeatureObservation>) -> FeatureFrame {
    FeatureFrame {
        t,
        camera: 0,
        features,
    }
}

/// The static scene's frame at `t`: every feature at its fixed pixel.
fn static_frame(t: f64) -> FeatureFrame {
    frame_with(
        t,
        PIXELS
            .iter()
            .zip(1u64..)
            .map(|(&(u, v), id)| observation(id, u, v))
            .collect(),
    )
}

fn initial_state() -> InitialState {
    InitialState {
        t: 0.0,
        rot: Matrix3::identity(),
        pos: Vector3::zeros(),
        vel: Vector3::zeros(),
        bias_gyro: Vector3::zeros(),
        bias_accel: Vector3::zeros(),
        sigma_ori_rad: 0.017,
        sigma_yaw_rad: None,
        sigma_pos_m: 0.05,
        sigma_vel_mps: 0.01,
        sigma_bias_gyro: 0.02,
        sigma_bias_accel: 0.02,
    }
}

fn new_estimator() -> Estimator {
    Estimator::new(EstimatorOptions::default(), CameraCalibration::euroc_cam0())
}

/// One estimator fed the static scenario, IMU sample by sample and frame by frame.
struct Robot {
    est: Estimator,
    /// Index of the next IMU sample (time `k / 400`).
    next_imu: u32,
    /// Index of the next frame (time `j / 10`).
    next_frame: u32,
}

impl Robot {
    /// Initialized at t = 0 with the first IMU sample fed.
    fn initialized() -> Self {
        let mut est = new_estimator();
        est.initialize(&initial_state());
        let mut robot = Self {
            est,
            next_imu: 0,
            next_frame: 1,
        };
        robot.feed_imu_until(0);
        robot
    }

    fn imu_time(k: u32) -> f64 {
        f64::from(k) / f64::from(IMU_HZ)
    }

    fn frame_time(j: u32) -> f64 {
        f64::from(j * IMU_PER_FRAME) / f64::from(IMU_HZ)
    }

    /// Time of the last IMU sample fed.
    fn last_imu_time(&self) -> f64 {
        Self::imu_time(self.next_imu - 1)
    }

    /// Feeds the valid IMU samples up to index `k` (inclusive); each is accepted.
    fn feed_imu_until(&mut self, k: u32) {
        while self.next_imu <= k {
            let t = Self::imu_time(self.next_imu);
            assert_eq!(self.est.feed_imu(imu_at(t)), Ok(()), "valid IMU at t={t}");
            self.next_imu += 1;
        }
    }

    /// Feeds the IMU up to the next frame's time, then `frame` (or the static
    /// frame), which must be accepted, and polls.
    fn step_with(&mut self, frame: Option<FeatureFrame>) -> Vec<Result<FrameOutput, FrameError>> {
        let j = self.next_frame;
        self.next_frame += 1;
        self.feed_imu_until(j * IMU_PER_FRAME);
        let frame = frame.unwrap_or_else(|| static_frame(Self::frame_time(j)));
        let t = frame.t;
        assert_eq!(self.est.feed_frame(frame), Ok(()), "valid frame at t={t}");
        self.est.poll()
    }

    /// One valid static frame; it must be processed with an output.
    fn step(&mut self) -> FrameOutput {
        let t = Self::frame_time(self.next_frame);
        let mut out = self.step_with(None);
        assert_eq!(out.len(), 1, "one frame queued and covered at t={t}");
        match out.pop() {
            Some(Ok(o)) => o,
            other => panic!("frame at t={t} not processed: {other:?}"),
        }
    }

    fn next_frame_time(&self) -> f64 {
        Self::frame_time(self.next_frame)
    }
}

/// Exact (bitwise for floats) equality of two frame outputs, timing aside.
fn assert_same_output(a: &FrameOutput, b: &FrameOutput) {
    assert_eq!(a.t().to_bits(), b.t().to_bits(), "time");
    assert_eq!(a.rot, b.rot, "orientation at t={}", a.t());
    assert_eq!(a.pos, b.pos, "position at t={}", a.t());
    assert_eq!(a.imu.vel, b.imu.vel, "velocity at t={}", a.t());
    assert_eq!(
        a.cov_ori,
        b.cov_ori,
        "orientation covariance at t={}",
        a.t()
    );
    assert_eq!(a.cov_pos, b.cov_pos, "position covariance at t={}", a.t());
    assert_eq!(
        a.record.msckf_features, b.record.msckf_features,
        "MSCKF features"
    );
    assert_eq!(
        a.record.slam_features, b.record.slam_features,
        "SLAM features"
    );
}

/// A sane estimate of the robot standing at the origin.
fn assert_plausible(o: &FrameOutput) {
    assert!(o.pos.iter().all(|v| v.is_finite()), "{o:?}");
    assert!(o.rot.iter().all(|v| v.is_finite()), "{o:?}");
    assert!(o.pos.norm() < 1.0, "a standing robot drifted to {}", o.pos);
    for c in [&o.cov_ori, &o.cov_pos] {
        assert!(c.iter().all(|v| v.is_finite()), "{o:?}");
        assert!((0..3).all(|i| c[(i, i)] > 0.0), "{o:?}");
    }
}

/// Runs `frames_before` frames on a robot and its twin, lets `corrupt` feed bad
/// input to the robot only (it asserts the rejections), then checks that both
/// accept the same valid stream for `frames_after` frames with identical output.
fn rejected_input_changes_nothing(
    frames_before: u32,
    frames_after: u32,
    corrupt: impl FnOnce(&mut Robot),
) {
    let mut robot = Robot::initialized();
    let mut twin = Robot::initialized();
    for _ in 0..frames_before {
        assert_same_output(&robot.step(), &twin.step());
    }
    corrupt(&mut robot);
    for _ in 0..frames_after {
        let (a, b) = (robot.step(), twin.step());
        assert_plausible(&a);
        assert_same_output(&a, &b);
    }
}

#[test]
fn the_static_scenario_is_processed_frame_by_frame_with_a_sane_estimate() {
    let mut robot = Robot::initialized();
    for _ in 0..30 {
        let o = robot.step();
        assert_plausible(&o);
    }
}

#[test]
fn an_imu_sample_with_a_nan_gyro_is_rejected_as_non_finite() {
    rejected_input_changes_nothing(3, 5, |r| {
        let mut s = imu_at(r.last_imu_time() + 0.5 / f64::from(IMU_HZ));
        s.gyro.y = f64::NAN;
        assert!(matches!(
            r.est.feed_imu(s),
            Err(InputError::NonFinite { .. })
        ));
    });
}

#[test]
fn an_imu_sample_with_an_infinite_accel_is_rejected_as_non_finite() {
    rejected_input_changes_nothing(3, 5, |r| {
        for bad in [f64::INFINITY, f64::NEG_INFINITY] {
            let mut s = imu_at(r.last_imu_time() + 0.5 / f64::from(IMU_HZ));
            s.accel.z = bad;
            assert!(matches!(
                r.est.feed_imu(s),
                Err(InputError::NonFinite { .. })
            ));
        }
    });
}

#[test]
fn an_imu_sample_with_a_nan_time_is_rejected_as_non_finite() {
    rejected_input_changes_nothing(3, 5, |r| {
        let err = r.est.feed_imu(imu_at(f64::NAN));
        assert!(
            matches!(err, Err(InputError::NonFinite { t, .. }) if t.is_nan()),
            "{err:?}"
        );
        let err = r.est.feed_imu(imu_at(f64::INFINITY));
        assert!(matches!(err, Err(InputError::NonFinite { .. })), "{err:?}");
    });
}

#[test]
fn an_imu_sample_going_back_in_time_is_rejected_as_time_backwards() {
    rejected_input_changes_nothing(3, 5, |r| {
        let last = r.last_imu_time();
        for t in [last - 0.01, 0.0, -1.0] {
            let err = r.est.feed_imu(imu_at(t));
            assert!(
                matches!(err, Err(InputError::TimeBackwards { t: at, previous, .. })
                    if at == t && previous == last),
                "{err:?}"
            );
        }
    });
}

#[test]
fn an_imu_sample_repeating_the_previous_time_is_rejected_as_time_backwards() {
    rejected_input_changes_nothing(3, 5, |r| {
        let last = r.last_imu_time();
        // Even with different readings: the time stamp is what is wrong.
        let mut s = imu_at(last);
        s.gyro.x = 0.3;
        let err = r.est.feed_imu(s);
        assert!(
            matches!(err, Err(InputError::TimeBackwards { t, previous, .. }) if t == last && previous == last),
            "{err:?}"
        );
    });
}

#[test]
fn an_imu_gap_larger_than_the_maximum_is_rejected_as_imu_gap() {
    let max_gap = EstimatorOptions::default().max_imu_gap_s;
    rejected_input_changes_nothing(3, 5, |r| {
        let last = r.last_imu_time();
        let t = last + 1.5 * max_gap;
        let err = r.est.feed_imu(imu_at(t));
        assert!(
            matches!(err, Err(InputError::ImuGap { gap_s, t: at, max_s })
                if (gap_s - 1.5 * max_gap).abs() < 1e-9 && at == t && max_s == max_gap),
            "{err:?}"
        );
    });
}

#[test]
fn an_imu_gap_within_the_maximum_is_accepted() {
    let mut est = new_estimator();
    est.initialize(&initial_state());
    let max_gap = est.options().max_imu_gap_s;
    assert_eq!(est.feed_imu(imu_at(0.0)), Ok(()));
    assert_eq!(est.feed_imu(imu_at(0.9 * max_gap)), Ok(()));
}

#[test]
fn a_frame_without_features_is_rejected_as_empty() {
    rejected_input_changes_nothing(3, 5, |r| {
        let t = r.next_frame_time();
        let err = r.est.feed_frame(frame_with(t, Vec::new()));
        assert_eq!(err, Err(InputError::EmptyFrame { t }));
        assert!(r.est.poll().is_empty(), "nothing queued");
    });
}

#[test]
fn a_frame_with_a_nan_pixel_is_rejected_as_non_finite() {
    rejected_input_changes_nothing(3, 5, |r| {
        let t = r.next_frame_time();
        for (u, v) in [(f64::NAN, 100.0), (100.0, f64::INFINITY)] {
            let mut f = static_frame(t);
            f.features[2] = observation(3, u, v);
            let err = r.est.feed_frame(f);
            assert!(
                matches!(err, Err(InputError::NonFinite { t: at, .. }) if at == t),
                "{err:?}"
            );
        }
        let err = r.est.feed_frame(static_frame(f64::NAN));
        assert!(matches!(err, Err(InputError::NonFinite { .. })), "{err:?}");
        assert!(r.est.poll().is_empty(), "nothing queued");
    });
}

#[test]
fn a_frame_older_than_the_previous_frame_is_rejected_as_time_backwards() {
    rejected_input_changes_nothing(3, 5, |r| {
        // The previous frame (at 0.3 s) was processed: older and equal times fail.
        let previous = Robot::frame_time(r.next_frame - 1);
        for t in [previous - 0.05, previous] {
            let err = r.est.feed_frame(static_frame(t));
            assert!(
                matches!(err, Err(InputError::TimeBackwards { t: at, previous: p, .. })
                    if at == t && p == previous),
                "{err:?}"
            );
        }
    });
}

#[test]
fn a_frame_older_than_a_queued_frame_is_rejected_as_time_backwards() {
    let mut robot = Robot::initialized();
    let mut twin = Robot::initialized();
    for _ in 0..2 {
        assert_same_output(&robot.step(), &twin.step());
    }
    // Queue the next frame before the IMU covers it, then try an older one.
    let queued = robot.next_frame_time();
    assert_eq!(robot.est.feed_frame(static_frame(queued)), Ok(()));
    let err = robot.est.feed_frame(static_frame(queued - 0.02));
    assert!(
        matches!(err, Err(InputError::TimeBackwards { previous, .. }) if previous == queued),
        "{err:?}"
    );
    // The IMU arrives; the queued frame is processed like the twin's.
    let j = robot.next_frame;
    robot.next_frame += 1;
    robot.feed_imu_until(j * IMU_PER_FRAME);
    let mut out = robot.est.poll();
    assert_eq!(out.len(), 1);
    let a = out
        .pop()
        .and_then(Result::ok)
        .expect("queued frame processed");
    assert_same_output(&a, &twin.step());
    for _ in 0..3 {
        assert_same_output(&robot.step(), &twin.step());
    }
}

#[test]
fn a_frame_repeating_a_feature_id_is_rejected_as_duplicate_id() {
    rejected_input_changes_nothing(3, 5, |r| {
        let t = r.next_frame_time();
        let mut f = static_frame(t);
        f.features.push(observation(5, 300.0, 300.0));
        assert_eq!(
            r.est.feed_frame(f),
            Err(InputError::DuplicateId { t, id: 5 })
        );
        // The same pixel twice is still a duplicate.
        let mut f = static_frame(t);
        f.features.push(f.features[0]);
        assert_eq!(
            r.est.feed_frame(f),
            Err(InputError::DuplicateId { t, id: 1 })
        );
    });
}

#[test]
fn a_feature_jumping_400_px_restarts_its_track_and_the_frame_is_processed() {
    let mut robot = Robot::initialized();
    for _ in 0..4 {
        robot.step();
    }
    // Features 1 (at 100, 80) and 4 (at 120, 400) jump 400 px to the right between
    // two frames, and stay there.
    let jumped = |t: f64| {
        let mut f = static_frame(t);
        f.features[0].uv.x += 400.0;
        f.features[3].uv.x += 400.0;
        f
    };
    let f = jumped(robot.next_frame_time());
    assert_eq!(f.features[0].uv, Vector2::new(500.0, 80.0));
    let out = robot.step_with(Some(f));
    assert_eq!(out.len(), 1, "{out:?}");
    match &out[0] {
        Ok(o) => assert_plausible(o),
        Err(e) => panic!("frame with a pixel jump not processed: {e}"),
    }
    // The restarted tracks go on at their new pixels.
    for _ in 0..5 {
        let f = jumped(robot.next_frame_time());
        let out = robot.step_with(Some(f));
        assert!(matches!(out.as_slice(), [Ok(_)]), "{out:?}");
        if let [Ok(o)] = out.as_slice() {
            assert_plausible(o);
        }
    }
}

#[test]
fn a_frame_before_initialization_is_dropped_as_not_initialized() {
    let mut est = new_estimator();
    for k in 0..=IMU_PER_FRAME {
        assert_eq!(est.feed_imu(imu_at(Robot::imu_time(k))), Ok(()));
    }
    let t = Robot::frame_time(1);
    assert_eq!(est.feed_frame(static_frame(t)), Ok(()));
    assert_eq!(
        est.poll().into_iter().map(|r| r.err()).collect::<Vec<_>>(),
        vec![Some(FrameError::NotInitialized(t))]
    );
    assert!(est.state().is_none());
    // Initialized later, the estimator works from then on.
    est.initialize(&InitialState {
        t: Robot::imu_time(IMU_PER_FRAME),
        ..initial_state()
    });
    for j in 2..6 {
        for k in ((j - 1) * IMU_PER_FRAME + 1)..=(j * IMU_PER_FRAME) {
            assert_eq!(est.feed_imu(imu_at(Robot::imu_time(k))), Ok(()));
        }
        let t = Robot::frame_time(j);
        assert_eq!(est.feed_frame(static_frame(t)), Ok(()));
        let out = est.poll();
        assert!(matches!(out.as_slice(), [Ok(_)]), "frame at t={t}: {out:?}");
        if let [Ok(o)] = out.as_slice() {
            assert_plausible(o);
        }
    }
}

#[test]
fn a_frame_without_imu_yet_waits_in_the_queue_until_the_imu_covers_it() {
    let mut robot = Robot::initialized();
    robot.step();
    let t = robot.next_frame_time();
    assert_eq!(robot.est.feed_frame(static_frame(t)), Ok(()));
    assert!(robot.est.poll().is_empty(), "IMU does not reach t={t} yet");
    let j = robot.next_frame;
    robot.next_frame += 1;
    robot.feed_imu_until(j * IMU_PER_FRAME);
    let out = robot.est.poll();
    assert!(matches!(out.as_slice(), [Ok(_)]), "{out:?}");
}
