//! Step 1 of a frame: matching our features to the peers' current frames and
//! to their keyframe databases, verified matches becoming links.

use super::loop_closure::{describe, detect, FrameFeatures, KeyframeDb, LoopClosure, LoopParams};
use super::matcher::{epipolar_inliers, match_descriptors, MatchRules};
use super::peer_frames::{alignment_options, frame_entry, measure};
use super::{Cooperation, Link, LinkSource, Peers};
use crate::estimator::peer_frame_states::FrameSeed;
use crate::peer_history::PeerHistory;
use common::descriptor::Descriptor;
use common::epipolar::{fundamental_eight_point, sampson_distance};
use nalgebra::Vector2;
use std::collections::HashMap;
use std::sync::Arc;
use vocabulary::MatchParams;

impl Cooperation {
    /// Step 1: links our current frame's tracks to the peers' (see the module
    /// documentation). `frame_seq` seeds the RANSAC.
    pub fn match_frame(&mut self, frame: &FrameFeatures, peers: &Peers, frame_seq: u64) {
        if frame.ids.is_empty() {
            return;
        }
        let threshold = self.opts.epipolar_threshold_px / self.focal_px;
        let rules = MatchRules {
            max_distance: self.opts.max_descriptor_distance_bits,
            ratio: self.opts.match_ratio,
        };
        if self.opts.common_vio || self.opts.common_slam {
            // A peer that stopped publishing (landed, left, died) leaves its
            // last frame behind: that is history, not a window seen now.
            let live: Vec<u32> = peers
                .iter()
                .filter(|(_, h)| {
                    h.recent()
                        .back()
                        .is_some_and(|f| frame.t_s - f.t_s <= self.opts.max_window_age_s)
                })
                .map(|(p, _)| *p)
                .collect();
            for peer in self.in_turn(&live, frame_seq) {
                if let Some(h) = peers.get(&peer) {
                    self.match_window(peer, h, frame, &rules, threshold, frame_seq);
                }
            }
        }
        if self.opts.historical {
            self.match_history(frame, peers, threshold, frame_seq);
        }
    }

    /// The peers of `eligible` (sorted ids) matched in frame `seq`: all of them,
    /// or `max_peers_matched_per_frame` taken in turn.
    fn in_turn(&self, eligible: &[u32], seq: u64) -> Vec<u32> {
        let k = self.opts.max_peers_matched_per_frame.max(1);
        let n = eligible.len();
        if n <= k {
            return eligible.to_vec();
        }
        let start = (seq as usize).wrapping_mul(k) % n;
        (0..k).map(|i| eligible[(start + i) % n]).collect()
    }

    /// Matches our frame to the peer's newest frame.
    fn match_window(
        &mut self,
        peer: u32,
        h: &PeerHistory,
        frame: &FrameFeatures,
        rules: &MatchRules,
        threshold: f64,
        seq: u64,
    ) {
        let Some(newest) = h.recent().back() else {
            return;
        };
        let latest_kf = h.keyframes.values().next_back();
        let known: HashMap<u64, Descriptor> = latest_kf
            .into_iter()
            .flat_map(|k| k.descriptors.iter().map(|e| (e.id, e.descriptor())))
            .chain(
                h.recent_descriptors
                    .iter()
                    .map(|(id, (_, bits))| (*id, Descriptor(*bits))),
            )
            .collect();
        // Pairs linked before and seen in both frames: their geometry is
        // already verified, only the new tracks need descriptor matching.
        let peer_xy: HashMap<u64, Vector2<f64>> =
            newest.features.iter().map(|p| (p.id, p.xy())).collect();
        let (mut linked1, mut linked2) = (Vec::new(), Vec::new());
        let mut linked_theirs = std::collections::HashSet::new();
        let mut unlinked: Vec<usize> = Vec::new();
        for (a, id) in frame.ids.iter().enumerate() {
            let mut found = false;
            for l in self.links_of(*id) {
                if l.peer == peer && l.source == LinkSource::Window {
                    if let Some(x) = peer_xy.get(&l.peer_track) {
                        linked1.push(frame.xy[a]);
                        linked2.push(*x);
                        linked_theirs.insert(l.peer_track);
                        found = true;
                    }
                }
            }
            if !found {
                unlinked.push(a);
            }
        }
        let (mut ids, mut desc, mut xy) = (vec![], vec![], vec![]);
        for p in &newest.features {
            if linked_theirs.contains(&p.id) {
                continue;
            }
            if let Some(d) = known.get(&p.id) {
                ids.push(p.id);
                desc.push(*d);
                xy.push(p.xy());
            }
        }
        let ours: Vec<Descriptor> = unlinked.iter().map(|a| frame.descriptors[*a]).collect();
        let pairs: Vec<(usize, usize)> = match_descriptors(&ours, &desc, rules)
            .into_iter()
            .map(|(i, j)| (unlinked[i], j))
            .collect();
        if pairs.is_empty() {
            return;
        }
        let x1: Vec<Vector2<f64>> = pairs.iter().map(|(a, _)| frame.xy[*a]).collect();
        let x2: Vec<Vector2<f64>> = pairs.iter().map(|(_, b)| xy[*b]).collect();
        let keep = if linked1.len() >= self.opts.min_window_inliers {
            // The geometry of the verified pairs (one least-squares solve) checks
            // the new ones; no RANSAC.
            match fundamental_eight_point(&linked1, &linked2) {
                Ok(f) => x1
                    .iter()
                    .zip(&x2)
                    .map(|(a, b)| sampson_distance(&f, a, b) <= threshold)
                    .collect(),
                Err(_) => return,
            }
        } else {
            let all1: Vec<Vector2<f64>> = linked1.iter().chain(&x1).copied().collect();
            let all2: Vec<Vector2<f64>> = linked2.iter().chain(&x2).copied().collect();
            let seed = seq.wrapping_mul(1_000_003) ^ u64::from(peer);
            let Some(inl) =
                epipolar_inliers(&all1, &all2, threshold, self.opts.min_window_inliers, seed)
            else {
                return;
            };
            inl[linked1.len()..].to_vec()
        };
        self.stats.window_matches += 1;
        for ((a, b), keep) in pairs.into_iter().zip(keep) {
            if keep {
                let link = Link {
                    peer,
                    peer_track: ids[b],
                    source: LinkSource::Window,
                };
                self.add_link(frame.ids[a], link);
            }
        }
    }

    /// How long a frame our state holds waits at `t_s` between two of its
    /// measurements: `held_frame_measurement_period_s`, stretched so that the
    /// frames in their measurement window together take at most
    /// `held_frame_measurements_per_s`.
    fn held_frame_period_s(&self, t_s: f64) -> f64 {
        let window = self.opts.held_frame_measurement_window_s;
        let measured = self
            .peers
            .iter()
            .flat_map(|(&peer, st)| st.frames.iter().map(move |(&epoch, f)| (peer, epoch, f)))
            .filter(|&(peer, epoch, f)| {
                f.alignment().is_some()
                    && self.holds_in_state(peer, epoch)
                    && f.confirmed_within(t_s, window)
            })
            .count();
        let period = self.opts.held_frame_measurement_period_s;
        period.max(measured as f64 / self.opts.held_frame_measurements_per_s)
    }

    /// Measures where peer `peer`'s frame is in ours from the loop closures
    /// `found` to its keyframe windows (see `peer_frames`).
    fn measure_frame(
        &mut self,
        peer: u32,
        h: &PeerHistory,
        frame: &FrameFeatures,
        found: &[LoopClosure],
        seq: u64,
    ) {
        let Some(camera) = frame.camera.as_ref() else {
            return;
        };
        let opts = alignment_options(&self.opts, frame.sigma_normalized);
        let confirmations = self.opts.alignment_confirmations;
        let focal = self.focal_px;
        let held_period = self.held_frame_period_s(frame.t_s);
        for lc in found {
            let Some(kf) = h.keyframes.get(&lc.keyframe) else {
                continue;
            };
            // Each of the peer's frames is measured on its own windows only.
            let epoch = kf.snapshot.frame_epoch;
            // A frame our state holds is corrected by the updates that use
            // its windows, and by the estimator with these measurements
            // (`held_frame_measurement_period_s`).
            let in_state = self.holds_in_state(peer, epoch);
            let peer_frame = frame_entry(&mut self.peers.entry(peer).or_default().frames, epoch);
            if !peer_frame.wants_measurement(frame.t_s) {
                continue;
            }
            if in_state && peer_frame.alignment().is_some() {
                let window = self.opts.held_frame_measurement_window_s;
                if self.opts.held_frame_measurement_period_s <= 0.0
                    || !peer_frame.confirmed_within(frame.t_s, window)
                    || !peer_frame.measured_before(frame.t_s - held_period)
                {
                    continue;
                }
                match measure(lc, kf, frame, camera, focal, &opts) {
                    Some(m) => {
                        peer_frame.note_measured(frame.t_s);
                        self.held_measurements.push(FrameSeed {
                            peer,
                            epoch,
                            clone: seq,
                            measurement: m,
                        });
                    }
                    None => peer_frame.failures += 1,
                }
                continue;
            }
            match measure(lc, kf, frame, camera, focal, &opts) {
                Some(m) => {
                    let was = peer_frame.alignment().is_some();
                    peer_frame.add(m.alignment, lc.keyframe, frame.t_s, confirmations);
                    if !was {
                        if let Some(a) = peer_frame.alignment() {
                            if in_state {
                                // The confirming measurement alone: its
                                // dependence on our pose is known.
                                self.seeds.push(FrameSeed {
                                    peer,
                                    epoch,
                                    clone: seq,
                                    measurement: m.clone(),
                                });
                            }
                            tracing::info!(
                                peer,
                                epoch,
                                yaw_deg = a.yaw_rad.to_degrees(),
                                t_m = ?a.t_m.as_slice(),
                                yaw_sigma_deg = a.yaw_sigma_rad().to_degrees(),
                                t_sigma_m = a.translation_sigma_m(),
                                "peer frame aligned"
                            );
                        }
                    }
                }
                None => peer_frame.failures += 1,
            }
        }
    }

    /// Indexes new peer keyframes and links our frame to the verified ones.
    fn match_history(&mut self, frame: &FrameFeatures, peers: &Peers, threshold: f64, seq: u64) {
        let Some(voc) = self.vocabulary.clone() else {
            return;
        };
        let (bow, index) = describe(&voc, frame);
        let params = LoopParams {
            candidates: self.opts.loop_candidates,
            min_score: self.opts.loop_min_score,
            matching: MatchParams {
                ratio: self.opts.match_ratio as f32,
                max_distance: self.opts.max_descriptor_distance_bits,
            },
            threshold,
            min_inliers: self.opts.min_loop_inliers,
            seed: seq,
        };
        let ids: Vec<u32> = peers.keys().copied().collect();
        let queried = self.in_turn(&ids, seq);
        for (&peer, h) in peers {
            let state = self.peers.entry(peer).or_default();
            let db = state
                .keyframes
                .get_or_insert_with(|| KeyframeDb::new(Arc::clone(&voc)));
            // Every peer's new keyframes are indexed (a loop closure may
            // find them later); only this frame's turn is queried.
            db.index_new(h);
            if !queried.contains(&peer) {
                continue;
            }
            let found = detect(db, h, frame, &bow, &index, &params);
            let candidates = params.candidates.min(db.len());
            let verified = found.len();
            self.stats.loop_closures += verified as u64;
            self.stats.loop_rejected += candidates.saturating_sub(verified) as u64;
            if self.opts.align_peer_frames {
                self.measure_frame(peer, h, frame, &found, seq);
            }
            for lc in found {
                for (ours, theirs) in lc.pairs {
                    let link = Link {
                        peer,
                        peer_track: theirs,
                        source: LinkSource::Keyframe(lc.keyframe),
                    };
                    self.add_link(ours, link);
                }
            }
        }
    }
}
