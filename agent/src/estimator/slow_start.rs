//! Slow platforms: a start that barely moves while its first window fills,
//! and a flight that turns slow later.
//!
//! At 0.1 m/s with points 5-7 m away, the first window's 1.1 s of frames sees
//! each point's rays about 1 deg apart, and nearly every track fails the
//! triangulation limits. The first update then takes the few that pass (or
//! all of them under looser limits), and its step, linearized at points whose
//! depth the window cannot tell, sends the filter off: V1_01 played at 0.3 of
//! its speed diverged in 3 of 10 runs without SLAM features and 2 of 10 with
//! them (README, Slow flights).
//!
//! Such a first update waits instead, up to [`MAX_WAIT_S`], and the window
//! keeps keyframes from then on (`EstimatorOptions::slow_start_keyframe_px`,
//! the rule of `keyframe_parallax_px`), so that it gains the baseline a
//! consecutive window lacks. Whether the start is slow is read from the window
//! itself: the parallax between its oldest and newest clones is under
//! [`WINDOW_PARALLAX_FACTOR`] keyframes' worth, and fewer than one candidate in
//! [`FAILED_PER_PASSED`] passes the limits. A start whose first window has that
//! parallax never waits: the reference tables (from the truth) and the
//! three-robot room are unchanged bit for bit. Six robots in their own frames
//! (20 seeds) changed in one seed, where one robot's first window waited.
//!
//! A start that waited is a slow platform, so the filter also takes the other
//! settings for slow platforms from then on
//! (`EstimatorOptions::slow_platform_settings`, [`SlowStart::apply`]):
//! observability-constrained MSCKF and SLAM Jacobians and inverse-depth SLAM
//! features, which keep a slow flight's clones, corrected long after they
//! were cloned, from making the filter claim what it does not know.
//!
//! A flight can also turn slow after a start that had parallax (V1_02 played
//! at 0.3 of its speed). When its window spans less than
//! [`WINDOW_PARALLAX_FACTOR`] keyframes' parallax for [`SLOW_FLIGHT_S`] in a
//! row, the MSCKF's Jacobians are observability-constrained and the window
//! keeps keyframes from then on ([`SlowStart::observe_window`]; V1_02 at 0.3x
//! without SLAM features, 10 seeds: 0.239 m, position NEES 2.81 with the
//! constrained MSCKF alone, 0.143 m, 2.11 with the keyframe window too). The
//! window is not thinned when the rule acts: it keeps its clones and keeps
//! keyframes as new ones come (a window thinned at once starved the updates,
//! stop 75). The SLAM settings are not switched on mid-flight: taken there they
//! made one V1_02 run at 0.3x worse (0.19 -> 0.36 m).
//!
//! The centralized filter (`central/`) keeps one [`SlowStart`] per robot.

use super::chi2::Chi2Table;
use super::feature_classes::window_parallax_px;
use super::feature_db::FeatureDb;
use super::filter::Filter;
use super::options::{EstimatorOptions, FeatureRepresentation, MsckfJacobians};
use super::state::Means;
use super::triangulation::TriangulationOptions;
use super::updater_msckf::would_starve;

/// The first window is slow when it spans less parallax than this many
/// keyframes' (V1_01's first window: 5-7 px at 0.3 of its speed, about 9 px at
/// 0.4; no first window of the five reference flights from the truth, seeds
/// 1-20, both starves and spans less than 12 px).
pub const WINDOW_PARALLAX_FACTOR: f64 = 3.0;

/// A slow first update waits while more candidates than this fail the ray
/// limits for each one that passes. With ten, as for the looser first update
/// (`updater_msckf::RELAX_WHEN_FAILED_PER_PASSED`), V1_01 at 0.4 of its speed
/// took its first update on 13 tracks of 109 and diverged in one run of ten.
pub const FAILED_PER_PASSED: usize = 4;

/// The longest a first update waits, s. On a slow start the window gains its
/// baseline in 0.4-2.0 s (V1_01 at 0.3-0.5 of its speed). A start whose clones
/// are bent by its errors (a tilt and a gyro-bias error drawn from OpenVINS's
/// 1 deg / 0.02 prior) starves for that reason too, and every second of
/// waiting bends them further: there the looser first update should come
/// soon (V1_01 seed 18 from that prior, without SLAM features: 1.18 deg /
/// 0.094 m with no wait; a 2.8 s wait and one plain step, 3.52 deg / 1.03 m;
/// this bound and the iterated update, 2.11 deg / 0.105 m).
pub const MAX_WAIT_S: f64 = 2.5;

/// How long a window of a flight that did not start slowly must span little
/// parallax (under [`WINDOW_PARALLAX_FACTOR`] keyframes') before the flight
/// counts as slow, s. None of the five reference flights from the truth
/// comes to it (seeds 1-20; the longest such spans, seeds 1-2: 2.7-3.0 s on
/// udel_gore, V1_01 and tum_corridor1); V1_02 played at 0.3 of its speed
/// comes to it 6 s into its flight, and its windows span under 12 px in half
/// its frames.
pub const SLOW_FLIGHT_S: f64 = 4.0;

/// Whether, and since when, the filter's first update waited for parallax,
/// and whether the flight turned slow after its start.
#[derive(Clone, Copy, Debug, Default)]
pub struct SlowStart {
    since_s: Option<f64>,
    /// The wait ended at [`MAX_WAIT_S`], with the update still starved.
    timed_out: bool,
    /// Since when the window has spanned little parallax, after the first
    /// update ([`Self::observe_window`]).
    low_since_s: Option<f64>,
    /// The flight turned slow after its start.
    slow_flight: bool,
}

impl SlowStart {
    /// Whether the window keeps keyframes: the first update waited.
    pub fn keyframes(&self) -> bool {
        self.since_s.is_some()
    }

    /// Whether the first update is one plain step: it waited and tracks then
    /// passed. A late first update iterated from a truth start ran off as its
    /// features stopped triangulating at the moved clones (V1_01 at 0.4 of its
    /// speed, 10 seeds without SLAM features: 1.29 deg / 0.52 m, position NEES
    /// 25.5, against 0.40 deg / 0.12 m, 1.47 in one step). One that waited in
    /// vain is a start whose clones are bent, which the iterated (and, when its
    /// step leaves the rays apart, rescued) update is for (seed 18 of V1_01
    /// from OpenVINS's drawn prior diverged after the wait in one step).
    pub fn plain_first_update(&self) -> bool {
        self.keyframes() && !self.timed_out
    }

    /// The keyframe rule's parallax for this frame: `keyframe_parallax_px`, or
    /// at least `slow_start_keyframe_px` once the first update waited or the
    /// flight turned slow.
    pub fn keyframe_parallax_px(&self, opts: &EstimatorOptions) -> f64 {
        if self.keyframes() || self.slow_flight {
            opts.keyframe_parallax_px.max(opts.slow_start_keyframe_px)
        } else {
            opts.keyframe_parallax_px
        }
    }

    /// This frame's options: after a wait, the keyframe window and (with
    /// `slow_platform_settings`) the other settings for slow platforms, the
    /// MSCKF's and the SLAM features' Jacobians observability-constrained and
    /// new SLAM features as anchored inverse depths; after a flight turned slow
    /// later ([`Self::observe_window`]), the keyframe window and the constrained
    /// MSCKF Jacobians.
    /// A slow platform's clones are corrected long after they were cloned:
    /// there the first estimates make the filter claim what it does not know.
    pub fn apply(&self, opts: &mut EstimatorOptions) {
        opts.keyframe_parallax_px = self.keyframe_parallax_px(opts);
        if !opts.slow_platform_settings {
            return;
        }
        if self.keyframes() {
            opts.msckf_jacobians = MsckfJacobians::ObservabilityConstrained;
            opts.slam_jacobians = MsckfJacobians::ObservabilityConstrained;
            opts.feature_representation = FeatureRepresentation::AnchoredInverseDepth;
        } else if self.slow_flight {
            opts.msckf_jacobians = MsckfJacobians::ObservabilityConstrained;
        }
    }

    /// After the first update, on a start that did not wait: watches the
    /// window's parallax, and a flight whose window spans less than
    /// [`WINDOW_PARALLAX_FACTOR`] keyframes' parallax for [`SLOW_FLIGHT_S`] in
    /// a row is slow from then on (see [`Self::apply`]).
    /// A filter already configured with the constrained MSCKF and a keyframe
    /// window at least that coarse has nothing to gain from the rule, and
    /// skips the per-frame parallax.
    pub fn observe_window(&mut self, means: &Means, db: &FeatureDb, opts: &EstimatorOptions) {
        let nothing_to_switch = opts.msckf_jacobians == MsckfJacobians::ObservabilityConstrained
            && opts.keyframe_parallax_px >= opts.slow_start_keyframe_px;
        if !opts.slow_platform_settings || nothing_to_switch || self.slow_flight || self.keyframes()
        {
            return;
        }
        let low = window_parallax_px(db, means)
            .is_some_and(|px| px < WINDOW_PARALLAX_FACTOR * opts.slow_start_keyframe_px);
        if !low {
            self.low_since_s = None;
            return;
        }
        let since = *self.low_since_s.get_or_insert(means.t);
        if means.t - since >= SLOW_FLIGHT_S {
            tracing::info!(
                t = means.t,
                "slow flight: the MSCKF's Jacobians are observability-constrained and the window keeps keyframes from now on"
            );
            self.slow_flight = true;
        }
    }

    /// Whether the flight turned slow after its start ([`Self::observe_window`]).
    pub fn slow_flight(&self) -> bool {
        self.slow_flight
    }

    /// Whether the filter's first update, with the candidates `ids` (the
    /// MSCKF's and the SLAM candidates, which need their points as much),
    /// waits this frame (see the module's documentation). Call it only before
    /// the first update.
    #[allow(clippy::too_many_arguments)]
    pub fn first_update_waits<F: Filter + ?Sized>(
        &mut self,
        state: &F,
        db: &FeatureDb,
        ids: &[u64],
        opts: &EstimatorOptions,
        chi2: &Chi2Table,
        tri: &TriangulationOptions,
    ) -> bool {
        let keyframe_px = opts.slow_start_keyframe_px;
        let t = state.means().t;
        if keyframe_px <= 0.0 || self.timed_out {
            return false;
        }
        if self.since_s.is_some_and(|t0| t - t0 >= MAX_WAIT_S) {
            self.timed_out = true;
            return false;
        }
        // Once waiting, the window's growing parallax does not end the wait:
        // only tracks that pass do.
        let slow = self.keyframes()
            || window_parallax_px(db, state.means())
                .is_some_and(|px| px < WINDOW_PARALLAX_FACTOR * keyframe_px);
        let cap = opts.max_msckf_in_update;
        if !slow || !would_starve(state, db, ids, cap, opts, chi2, tri, FAILED_PER_PASSED) {
            return false;
        }
        if self.since_s.is_none() {
            tracing::info!(
                t,
                "slow start: the first update waits for parallax, the window keeps keyframes"
            );
            self.since_s = Some(t);
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;

    #[test]
    fn the_window_keeps_keyframes_and_the_update_is_one_step_only_after_a_wait() {
        let opts = EstimatorOptions {
            keyframe_parallax_px: 0.0,
            slow_start_keyframe_px: 4.0,
            ..EstimatorOptions::default()
        };
        let mut s = SlowStart::default();
        assert_eq!(s.keyframe_parallax_px(&opts), 0.0);
        assert!(!s.plain_first_update());
        s.since_s = Some(1.1);
        assert_eq!(s.keyframe_parallax_px(&opts), 4.0);
        assert!(s.plain_first_update());
        // A keyframe rule set for the whole run keeps its own, larger parallax.
        let set = EstimatorOptions {
            keyframe_parallax_px: 6.0,
            ..opts.clone()
        };
        assert_eq!(s.keyframe_parallax_px(&set), 6.0);
        // A wait that ended still starved leaves the iterated first update.
        s.timed_out = true;
        assert!(s.keyframes() && !s.plain_first_update());
    }

    #[test]
    fn only_a_start_that_waited_takes_the_settings_for_slow_platforms() {
        let defaults = EstimatorOptions::default();
        let mut s = SlowStart::default();
        let mut opts = defaults.clone();
        s.apply(&mut opts);
        assert_eq!(
            opts, defaults,
            "a start that never waited keeps its options"
        );

        s.since_s = Some(1.1);
        s.apply(&mut opts);
        assert_eq!(opts.keyframe_parallax_px, defaults.slow_start_keyframe_px);
        assert_eq!(
            opts.msckf_jacobians,
            MsckfJacobians::ObservabilityConstrained
        );
        assert_eq!(
            opts.slam_jacobians,
            MsckfJacobians::ObservabilityConstrained
        );
        assert_eq!(
            opts.feature_representation,
            FeatureRepresentation::AnchoredInverseDepth
        );

        // Switched off, the wait keeps only its keyframe window.
        let off = EstimatorOptions {
            slow_platform_settings: false,
            ..defaults.clone()
        };
        let mut opts = off.clone();
        s.apply(&mut opts);
        assert_eq!(opts.keyframe_parallax_px, off.slow_start_keyframe_px);
        assert_eq!(opts.msckf_jacobians, off.msckf_jacobians);
        assert_eq!(opts.slam_jacobians, off.slam_jacobians);
        assert_eq!(opts.feature_representation, off.feature_representation);
    }

    #[test]
    fn a_flight_whose_window_stays_without_parallax_takes_the_constrained_msckf_and_keyframes() {
        let s = scene(12, 12, 1e-4, 1e-4);
        let mut means = s.state.means.clone();
        // The scene's window spans metres: with a keyframe parallax this large it
        // counts as a window without parallax, with the default's as one with.
        let low = EstimatorOptions {
            slow_start_keyframe_px: 1e9,
            ..EstimatorOptions::default()
        };
        let high = EstimatorOptions::default();
        let mut watch = |slow: &mut SlowStart, t: f64, opts: &EstimatorOptions| {
            means.t = t;
            slow.observe_window(&means, &s.db, opts);
            slow.slow_flight()
        };

        let mut slow = SlowStart::default();
        assert!(!watch(&mut slow, 10.0, &low));
        assert!(!watch(&mut slow, 13.9, &low));
        // One window with parallax starts the count again.
        assert!(!watch(&mut slow, 14.0, &high));
        assert!(!watch(&mut slow, 14.1, &low));
        assert!(!watch(&mut slow, 18.0, &low));
        assert!(watch(&mut slow, 18.1, &low), "4 s without parallax");

        let mut opts = low.clone();
        slow.apply(&mut opts);
        let defaults = EstimatorOptions::default();
        assert_eq!(
            opts.msckf_jacobians,
            MsckfJacobians::ObservabilityConstrained
        );
        // Mid-flight the window keeps keyframes; the SLAM settings do not change.
        assert_eq!(opts.keyframe_parallax_px, low.slow_start_keyframe_px);
        assert_eq!(opts.slam_jacobians, defaults.slam_jacobians);
        assert_eq!(opts.feature_representation, defaults.feature_representation);

        // Switched off, a flight never turns slow.
        let off = EstimatorOptions {
            slow_platform_settings: false,
            ..low.clone()
        };
        let mut slow = SlowStart::default();
        for t in [0.0, 5.0, 10.0] {
            assert!(!watch(&mut slow, t, &off));
        }

        // Configured with the constrained MSCKF and that keyframe window
        // already, the rule has nothing to switch and does not watch; with the
        // constrained MSCKF alone it still switches the window.
        let constrained = EstimatorOptions {
            msckf_jacobians: MsckfJacobians::ObservabilityConstrained,
            ..low.clone()
        };
        let both = EstimatorOptions {
            keyframe_parallax_px: low.slow_start_keyframe_px,
            ..constrained.clone()
        };
        let mut slow = SlowStart::default();
        for t in [0.0, 5.0, 10.0] {
            assert!(!watch(&mut slow, t, &both));
        }
        let mut slow = SlowStart::default();
        assert!(!watch(&mut slow, 0.0, &constrained));
        assert!(watch(&mut slow, 4.0, &constrained));
    }
}
