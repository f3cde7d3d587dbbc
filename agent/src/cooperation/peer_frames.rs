//! Where each peer's world frame is in ours, for fleets whose robots were not
//! given their start poses in one frame (`align_peer_frames`).
//!
//! A peer's windows are of no use before its frame is known: the CI-EKF
//! compares its camera poses with ours. Loop closures need no frame (bag of
//! words, descriptors and the epipolar check), so they run from the start;
//! each verified one to an unaligned peer is turned into a measurement of the
//! alignment (`estimator::frame_alignment`): the peer's track triangulated in
//! its keyframe window, seen by our camera now.
//!
//! One measurement could come from a place that only looks like another
//! (perceptual aliasing), so a frame is taken only once
//! `alignment_confirmations` loop closures to different keyframe windows
//! agree on it (χ² gate). From then on the peer's windows are used, expressed
//! in our frame with the alignment's covariance, and further loop closures
//! refine it (covariance intersection, at most once a second); one that
//! disagrees is counted and dropped.

use super::loop_closure::{FrameFeatures, LoopClosure};
use crate::estimator::frame_alignment::{
    estimate_alignment, point_covariance, AlignmentMeasurement, AlignmentOptions, AlignmentPoint,
    CameraEstimate, FrameAlignment,
};
use crate::estimator::triangulation::{
    triangulate, CameraObservation, RayResidual, TriangulationOptions,
};
use crate::peer_history::KeyframeWindow;
use common::estimator_options::CooperationOptions;
use nalgebra::{Matrix3, SMatrix, Vector2};
use std::collections::{BTreeMap, BTreeSet};

/// χ²(4) at 99.9 %: two measurements of one alignment agree.
const AGREEMENT_GATE: f64 = 18.47;

/// An aligned peer's frame is refined at most this often, s (each
/// measurement costs a RANSAC and its covariance).
const REFINE_PERIOD_S: f64 = 1.0;

/// Unconfirmed candidates kept per peer.
const MAX_CANDIDATES: usize = 8;

/// Frames (starts) kept per peer: the epoch comes from the network, and a
/// peer that names a new one in every snapshot must not grow our memory.
pub const MAX_FRAMES_PER_PEER: usize = 8;

/// Peer frame `epoch` in `frames`, made when new; at most
/// [`MAX_FRAMES_PER_PEER`] are kept, a new one replacing first a frame never
/// confirmed, else the oldest start (the smallest epoch).
pub fn frame_entry(frames: &mut BTreeMap<u64, PeerFrame>, epoch: u64) -> &mut PeerFrame {
    if !frames.contains_key(&epoch) && frames.len() >= MAX_FRAMES_PER_PEER {
        let unconfirmed = frames.iter().find(|(_, f)| f.aligned.is_none());
        let evict = unconfirmed
            .or_else(|| frames.iter().next())
            .map(|(e, _)| *e);
        if let Some(e) = evict {
            frames.remove(&e);
        }
    }
    frames.entry(epoch).or_default()
}

/// A candidate frame: fused measurements and the keyframe windows they came from.
#[derive(Clone, Debug, PartialEq)]
struct Candidate {
    alignment: FrameAlignment,
    keyframes: BTreeSet<u64>,
}

/// What we know of one peer's frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PeerFrame {
    candidates: Vec<Candidate>,
    aligned: Option<FrameAlignment>,
    /// When the aligned frame was last refined (fleet clock), s.
    refined_at_s: Option<f64>,
    /// When the frame was confirmed (fleet clock), s.
    pub aligned_at_s: Option<f64>,
    /// Measurements taken in (fused into a candidate or the frame).
    pub measurements: u64,
    /// Measurements that disagreed with the aligned frame.
    pub disagreements: u64,
    /// Loop closures that gave no measurement (too few points agreed, or
    /// they placed the frame too loosely).
    pub failures: u64,
    /// Whether our filter holds the frame as states now
    /// (`cooperation.peer_frame_state_s`); its estimate is then the state's.
    pub in_filter: bool,
}

impl PeerFrame {
    /// The peer's frame in ours, once confirmed.
    pub fn alignment(&self) -> Option<&FrameAlignment> {
        self.aligned.as_ref()
    }

    /// The same record with `a` as the frame's estimate (the one our
    /// state holds).
    pub(crate) fn with_alignment(mut self, a: FrameAlignment) -> Self {
        self.aligned = Some(a);
        self
    }

    /// Whether a loop closure at `t_s` should be measured.
    pub fn wants_measurement(&self, t_s: f64) -> bool {
        self.aligned.is_none() || self.refined_at_s.is_none_or(|t| t_s - t >= REFINE_PERIOD_S)
    }

    /// Whether the frame was confirmed at most `window_s` before `t_s`.
    pub(crate) fn confirmed_within(&self, t_s: f64, window_s: f64) -> bool {
        self.aligned_at_s.is_some_and(|t| t_s - t <= window_s)
    }

    /// Whether the frame was last measured (or confirmed) at or before `t_s`.
    pub(crate) fn measured_before(&self, t_s: f64) -> bool {
        self.refined_at_s.is_none_or(|t| t <= t_s)
    }

    /// A measurement at `t_s` of a frame our state holds, handed to the
    /// estimator (it is not fused here). Counted as taken in, though the
    /// estimator's χ² gate (`updater_frame`) may still refuse it.
    pub(crate) fn note_measured(&mut self, t_s: f64) {
        self.refined_at_s = Some(t_s);
        self.measurements += 1;
    }

    /// Takes in a measurement from keyframe window `keyframe` at `t_s`.
    pub fn add(&mut self, m: FrameAlignment, keyframe: u64, t_s: f64, confirmations: usize) {
        if let Some(a) = self.aligned {
            self.refined_at_s = Some(t_s);
            match a.mahalanobis_sq(&m) {
                Some(d) if d <= AGREEMENT_GATE => {
                    if let Some(f) = a.fuse(&m) {
                        self.aligned = Some(f);
                        self.measurements += 1;
                    }
                }
                _ => self.disagreements += 1,
            }
            return;
        }
        self.measurements += 1;
        let agreeing = self.candidates.iter_mut().find(|c| {
            c.alignment
                .mahalanobis_sq(&m)
                .is_some_and(|d| d <= AGREEMENT_GATE)
        });
        match agreeing {
            Some(c) => {
                if let Some(f) = c.alignment.fuse(&m) {
                    c.alignment = f;
                }
                c.keyframes.insert(keyframe);
                if c.keyframes.len() >= confirmations.max(1) {
                    self.aligned = Some(c.alignment);
                    self.refined_at_s = Some(t_s);
                    self.aligned_at_s = Some(t_s);
                    self.candidates.clear();
                }
            }
            None => {
                if confirmations <= 1 {
                    self.aligned = Some(m);
                    self.refined_at_s = Some(t_s);
                    self.aligned_at_s = Some(t_s);
                    return;
                }
                if self.candidates.len() >= MAX_CANDIDATES {
                    self.candidates.remove(0);
                }
                self.candidates.push(Candidate {
                    alignment: m,
                    keyframes: BTreeSet::from([keyframe]),
                });
            }
        }
    }
}

/// The alignment options of `opts` for our normalized pixel noise `sigma`.
pub fn alignment_options(opts: &CooperationOptions, sigma: f64) -> AlignmentOptions {
    AlignmentOptions {
        sigma_normalized: sigma,
        min_inliers: opts.min_alignment_inliers,
        max_yaw_sigma_rad: opts.max_alignment_yaw_sigma_deg.to_radians(),
        max_translation_sigma_m: opts.max_alignment_translation_sigma_m,
        ..AlignmentOptions::default()
    }
}

/// The peer's keyframe camera (the window's newest clone) with its covariance.
fn anchor_of(kf: &KeyframeWindow) -> Option<CameraEstimate> {
    let snap = &kf.snapshot;
    let i = snap.clones.len().checked_sub(1)?;
    let c = snap.clones.last()?;
    let mut cov = SMatrix::<f64, 6, 6>::zeros();
    for r in 0..6 {
        for k in 0..6 {
            cov[(r, k)] = snap.covariance.get(6 * i + r, 6 * i + k)?;
        }
    }
    Some(CameraEstimate {
        rot: c.rot_c_to_g(),
        pos: c.p_c_in_g(),
        cov,
    })
}

/// The alignment measured by loop closure `lc` to keyframe window `kf`: each
/// pair's peer track triangulated from the window's measurements, seen by
/// our track in `frame`, from `camera` (our camera now, of focal length
/// `our_focal_px`). `None` when it does not give one (too few points, too
/// uncertain, ...).
pub fn measure(
    lc: &LoopClosure,
    kf: &KeyframeWindow,
    frame: &FrameFeatures,
    camera: &CameraEstimate,
    our_focal_px: f64,
    opts: &AlignmentOptions,
) -> Option<AlignmentMeasurement> {
    let anchor = anchor_of(kf)?;
    // The peer's measurements are normalized with its own intrinsics; its
    // pixel noise is ours scaled to the noise its window declares, over its
    // focal length, and its rays are triangulated as its lens spreads its
    // pixels (`RayResidual::of`).
    let peer_camera = kf.snapshot.camera.to_camera_model().ok()?;
    let peer_focal = Some((peer_camera.fx() * peer_camera.fy()).sqrt()).filter(|f| *f > 0.0)?;
    let noise_ratio = if frame.pixel_sigma_px > 0.0 {
        kf.snapshot.pixel_sigma_px / frame.pixel_sigma_px
    } else {
        1.0
    };
    let peer_sigma = opts.sigma_normalized * our_focal_px * noise_ratio / peer_focal;
    let poses: Vec<(f64, Matrix3<f64>, nalgebra::Vector3<f64>)> = kf
        .snapshot
        .clones
        .iter()
        .map(|c| (c.t_s, c.rot_c_to_g(), c.p_c_in_g()))
        .collect();
    let tri = TriangulationOptions {
        residual: RayResidual::of(&peer_camera),
        ..TriangulationOptions::default()
    };
    let ours: std::collections::HashMap<u64, Vector2<f64>> = frame
        .ids
        .iter()
        .copied()
        .zip(frame.xy.iter().copied())
        .collect();
    let mut points = Vec::with_capacity(lc.pairs.len());
    for (our, theirs) in &lc.pairs {
        let Some(xy) = ours.get(our) else { continue };
        let obs: Vec<CameraObservation> = kf
            .measurements_of(*theirs)
            .filter_map(|(t, m)| {
                let (_, r, p) = poses.iter().find(|(tc, _, _)| (tc - t).abs() < 1e-6)?;
                Some(CameraObservation {
                    r_c_to_g: *r,
                    p_c_in_g: *p,
                    uvn: Vector2::new(f64::from(m[0]), f64::from(m[1])),
                })
            })
            .collect();
        let Ok(p) = triangulate(&obs, &tri) else {
            continue;
        };
        let cams: Vec<_> = obs.iter().map(|o| (o.r_c_to_g, o.p_c_in_g)).collect();
        let Some(cov) = point_covariance(&cams, &p, peer_sigma) else {
            continue;
        };
        let r_t = anchor.rot.transpose();
        points.push(AlignmentPoint {
            in_anchor: r_t * (p - anchor.pos),
            cov_in_anchor: r_t * cov * anchor.rot,
            xy: *xy,
        });
    }
    match estimate_alignment(camera, &anchor, &points, opts) {
        Ok(m) => Some(m),
        Err(e) => {
            // Why a peer frame stays unaligned, for whoever reads the log.
            tracing::debug!(
                keyframe = lc.keyframe,
                pairs = lc.pairs.len(),
                points = points.len(),
                "no alignment from the loop closure: {e}"
            );
            None
        }
    }
}

/// How well the peers' frames were aligned, against their true places.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameScore {
    /// Peer frames aligned (a peer started again in a new frame counts each).
    pub aligned: u64,
    /// Root mean square yaw error over the aligned frames with a truth, deg.
    pub yaw_err_deg: Option<f64>,
    /// Root mean square translation error, m.
    pub pos_err_m: Option<f64>,
    /// Mean NEES of `[δψ, δt]` (4 DoF).
    pub nees: Option<f64>,
    /// Earliest confirmation (fleet clock), s.
    pub first_aligned_at_s: Option<f64>,
}

/// Scores `frames` (per peer, per frame epoch) against `truth`, each peer's
/// true `(yaw, translation)` of its frame in ours (`None`: unknown; a
/// simulated robot started again starts from the same pose, so its frames
/// share one truth).
pub fn score(
    frames: &BTreeMap<u32, BTreeMap<u64, PeerFrame>>,
    truth: impl Fn(u32) -> Option<(f64, nalgebra::Vector3<f64>)>,
) -> FrameScore {
    let mut out = FrameScore::default();
    let (mut yaw_sq, mut pos_sq, mut nees, mut n) = (0.0, 0.0, 0.0, 0usize);
    let each = frames
        .iter()
        .flat_map(|(peer, epochs)| epochs.values().map(move |f| (peer, f)));
    for (peer, f) in each {
        let Some(a) = f.alignment() else { continue };
        out.aligned += 1;
        out.first_aligned_at_s = match (out.first_aligned_at_s, f.aligned_at_s) {
            (Some(x), Some(y)) => Some(x.min(y)),
            (x, y) => x.or(y),
        };
        let Some((yaw, t)) = truth(*peer) else {
            continue;
        };
        let truth = FrameAlignment {
            yaw_rad: yaw,
            t_m: t,
            cov: nalgebra::Matrix4::zeros(),
        };
        let e = truth.difference(a);
        yaw_sq += e[0] * e[0];
        pos_sq += e.fixed_rows::<3>(1).norm_squared();
        if let Some(d) = truth.mahalanobis_sq(a) {
            nees += d;
        }
        n += 1;
    }
    if n > 0 {
        let n = n as f64;
        out.yaw_err_deg = Some((yaw_sq / n).sqrt().to_degrees());
        out.pos_err_m = Some((pos_sq / n).sqrt());
        out.nees = Some(nees / n);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix4, Vector3, Vector4};

    fn alignment(yaw: f64, x: f64) -> FrameAlignment {
        FrameAlignment {
            yaw_rad: yaw,
            t_m: Vector3::new(x, 0.0, 0.0),
            cov: Matrix4::from_diagonal(&Vector4::new(1e-4, 1e-2, 1e-2, 1e-2)),
        }
    }

    #[test]
    fn a_frame_needs_agreeing_loop_closures_to_different_keyframes() {
        let mut f = PeerFrame::default();
        f.add(alignment(0.5, 1.0), 7, 10.0, 2);
        assert!(f.alignment().is_none());
        // The same keyframe again confirms nothing.
        f.add(alignment(0.501, 1.01), 7, 10.1, 2);
        assert!(f.alignment().is_none());
        // A disagreeing one starts its own candidate.
        f.add(alignment(1.5, -3.0), 8, 10.2, 2);
        assert!(f.alignment().is_none());
        f.add(alignment(0.499, 0.98), 9, 10.3, 2);
        let a = f.alignment().expect("confirmed");
        assert!((a.yaw_rad - 0.5).abs() < 0.01);
        assert_eq!(f.aligned_at_s, Some(10.3));
        assert_eq!(f.measurements, 4);
        // Held in our state, it is measured again only within the window.
        assert!(f.confirmed_within(70.3, 60.0));
        assert!(!f.confirmed_within(70.4, 60.0));
        assert!(f.confirmed_within(3600.0, f64::INFINITY));
        // Refined at most once a second; a wrong one is counted, not taken.
        assert!(!f.wants_measurement(10.8));
        assert!(f.wants_measurement(11.3));
        f.add(alignment(2.0, 5.0), 10, 11.3, 2);
        assert_eq!(f.disagreements, 1);
        assert!((f.alignment().expect("kept").yaw_rad - 0.5).abs() < 0.01);
    }

    #[test]
    fn a_score_compares_the_aligned_frames_with_the_truth() {
        let mut frames = BTreeMap::new();
        let mut f = PeerFrame::default();
        f.add(alignment(0.51, 1.1), 7, 12.0, 1);
        frames.insert(2, BTreeMap::from([(1, f)]));
        frames.insert(3, BTreeMap::from([(1, PeerFrame::default())]));
        let s = score(&frames, |p| {
            (p == 2).then(|| (0.5, Vector3::new(1.0, 0.0, 0.0)))
        });
        assert_eq!(s.aligned, 1);
        assert!((s.yaw_err_deg.expect("scored") - 0.01f64.to_degrees()).abs() < 1e-9);
        assert!((s.pos_err_m.expect("scored") - 0.1).abs() < 1e-9);
        // (0.01² / 1e-4 + 0.1² / 1e-2) = 2.
        assert!((s.nees.expect("scored") - 2.0).abs() < 1e-9);
        assert_eq!(s.first_aligned_at_s, Some(12.0));
    }

    #[test]
    fn a_peer_naming_new_frames_without_end_keeps_a_bounded_few() {
        let mut frames = BTreeMap::new();
        // Its real frame, confirmed.
        frame_entry(&mut frames, 5).add(alignment(0.5, 1.0), 7, 10.0, 1);
        for epoch in 100..1000 {
            frame_entry(&mut frames, epoch).failures += 1;
            assert!(frames.len() <= MAX_FRAMES_PER_PEER);
        }
        // The unconfirmed ones made room; the confirmed one stays.
        assert!(frames[&5].alignment().is_some());
        assert!(frames.contains_key(&999));
    }

    #[test]
    fn one_confirmation_takes_the_first_measurement() {
        let mut f = PeerFrame::default();
        f.add(alignment(0.5, 1.0), 7, 10.0, 1);
        assert!(f.alignment().is_some());
    }
}
