//! Cooperation on a small synthetic scene: a peer flew past landmarks (its
//! keyframe window is stored in its history, its newest frame is recent), and
//! our camera now sees the same landmarks from elsewhere.

use super::loop_closure::FrameFeatures;
use super::*;
use crate::estimator::frame_alignment::CameraEstimate;
use crate::peer_history::HistoryLimits;
use common::descriptor::Descriptor;
use common::messages::{
    CameraModelWire, CameraPose, DescriptorBatch, DescriptorEntry, PackedCovariance, StateSnapshot,
    TrackFrame, TrackPoint,
};
use nalgebra::Vector2;
use nalgebra::{DMatrix, Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A camera looking along world +y.
fn forward() -> Matrix3<f64> {
    Matrix3::from_columns(&[
        Vector3::new(1.0, 0.0, 0.0),
        Vector3::new(0.0, 0.0, -1.0),
        Vector3::new(0.0, 1.0, 0.0),
    ])
}

fn project(pos: &Vector3<f64>, p: &Vector3<f64>) -> Vector2<f64> {
    let c = forward().transpose() * (p - pos);
    Vector2::new(c.x / c.z, c.y / c.z)
}

struct World {
    landmarks: Vec<Vector3<f64>>,
    descriptors: Vec<Descriptor>,
}

fn world(n: usize, rng: &mut ChaCha8Rng) -> World {
    World {
        landmarks: (0..n)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-2.5..2.5),
                    rng.random_range(4.0..7.0),
                    rng.random_range(-1.5..1.5),
                )
            })
            .collect(),
        descriptors: (0..n)
            .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
            .collect(),
    }
}

fn noisy(d: &Descriptor, rng: &mut ChaCha8Rng) -> Descriptor {
    let mut d = *d;
    for _ in 0..8 {
        d.flip(rng.random_range(0..256));
    }
    d
}

/// The peer's track id of landmark `l` (peers number their tracks their way).
fn peer_track(l: usize) -> u64 {
    1000 + l as u64
}

/// A peer that flew 11 frames (t = 1.0 .. 2.0) along x and stored the window as
/// a keyframe (descriptors of every track), with a small covariance.
fn peer_history(w: &World, rng: &mut ChaCha8Rng) -> PeerHistory {
    peer_history_in(w, rng, 0)
}

/// [`peer_history`] with its window in the peer's frame `epoch` (in the
/// same place as ours).
fn peer_history_in(w: &World, rng: &mut ChaCha8Rng, epoch: u64) -> PeerHistory {
    let mut h = PeerHistory::default();
    let limits = HistoryLimits {
        max_bytes: usize::MAX,
        recent_s: 5.0,
        retention: Default::default(),
    };
    let mut clones = Vec::new();
    for k in 0..11 {
        let t = 1.0 + 0.1 * k as f64;
        let pos = Vector3::new(-1.0 + 0.1 * k as f64, 0.0, 0.4);
        clones.push(CameraPose::new(t, &forward(), &pos));
        let features = w
            .landmarks
            .iter()
            .enumerate()
            .map(|(l, p)| {
                let xy = project(&pos, p);
                TrackPoint::new(
                    peer_track(l),
                    &Vector2::new(460.0 * xy.x + 376.0, 460.0 * xy.y + 240.0),
                    &xy,
                )
            })
            .collect();
        h.add_tracks(
            TrackFrame {
                frame_index: k,
                t_s: t,
                features,
            },
            &limits,
        );
    }
    h.add_descriptors(
        DescriptorBatch {
            frame_index: 10,
            t_s: 2.0,
            keyframe: true,
            entries: w
                .descriptors
                .iter()
                .enumerate()
                .map(|(l, d)| DescriptorEntry::new(peer_track(l), noisy(d, rng)))
                .collect(),
        },
        &limits,
    );
    let snap = StateSnapshot {
        frame_index: 10,
        t_s: 2.0,
        keyframe: true,
        frame_epoch: epoch,
        camera: CameraModelWire::default(),
        pixel_sigma_px: 1.0,
        covariance: PackedCovariance::from_dmatrix(&(DMatrix::identity(66, 66) * 1e-4))
            .unwrap_or_default(),
        clones,
        landmarks: Vec::new(),
    };
    h.add_snapshot(snap, &limits);
    h
}

/// Our frame: landmarks `seen` from a camera 0.8 m to the right, our tracks
/// numbered 1, 2, ... in that order.
fn our_frame(w: &World, seen: &[usize], rng: &mut ChaCha8Rng) -> FrameFeatures {
    let pos = Vector3::new(0.8, -0.3, 0.0);
    // Just after the peer's newest frame (t = 2.0).
    let mut f = FrameFeatures {
        t_s: 2.1,
        ..FrameFeatures::default()
    };
    for (i, l) in seen.iter().enumerate() {
        f.ids.push(i as u64 + 1);
        f.descriptors.push(noisy(&w.descriptors[*l], rng));
        f.xy.push(project(&pos, &w.landmarks[*l]));
    }
    f
}

fn options() -> CooperationOptions {
    CooperationOptions {
        common_vio: true,
        common_slam: true,
        historical: true,
        ..CooperationOptions::default()
    }
}

#[test]
fn our_tracks_are_linked_to_the_peers_tracks_of_the_same_landmarks() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let w = world(40, &mut rng);
    let peers: Peers = [(7u32, peer_history(&w, &mut rng))].into_iter().collect();
    let seen: Vec<usize> = (5..35).collect();
    let frame = our_frame(&w, &seen, &mut rng);
    let mut coop = Cooperation::new(options(), None, 460.0);
    coop.match_frame(&frame, &peers, 1);
    assert_eq!(coop.stats.window_matches, 1);
    let mut right = 0;
    for (i, l) in seen.iter().enumerate() {
        for link in coop.links_of(i as u64 + 1) {
            assert_eq!(link.peer, 7);
            assert_eq!(link.peer_track, peer_track(*l), "our track {}", i + 1);
            right += 1;
        }
    }
    assert!(right >= 25, "{right} of 30 tracks linked");
}

#[test]
fn a_peer_track_gives_a_common_slam_update_its_newest_view_only_when_asked() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let w = world(40, &mut rng);
    let peers: Peers = [(7u32, peer_history(&w, &mut rng))].into_iter().collect();
    let frame = our_frame(&w, &(5..35).collect::<Vec<_>>(), &mut rng);
    let views = |newest: Option<bool>| {
        let opts = CooperationOptions {
            peer_slam_newest_view: newest,
            ..options()
        };
        let mut coop = Cooperation::new(opts, None, 460.0);
        coop.match_frame(&frame, &peers, 1);
        let id = (1..=30u64)
            .find(|id| !coop.links_of(*id).is_empty())
            .expect("a linked track");
        let ev = coop.evidence(&[], &[id], &peers);
        let obs = ev.slam[0].peer_obs.clone();
        coop.mark_used(&ev, &[], &[id], &[]);
        let again = coop.evidence(&[], &[id], &peers);
        (obs, ev.participants, again.slam.len())
    };
    // Every view of the peer's 11-frame window, as independent measurements.
    let (all, _, _) = views(None);
    assert_eq!(all.len(), 11);
    // Only the newest; the older views are used up with it, never counted.
    let (newest, participants, again) = views(Some(true));
    assert_eq!(newest.len(), 1);
    let last = participants[newest[0].participant].poses.len() - 1;
    assert_eq!(newest[0].pose, last);
    assert_eq!(newest[0].xy, all.iter().max_by_key(|o| o.pose).unwrap().xy);
    assert_eq!(again, 0);
}

#[test]
fn a_peer_that_stopped_publishing_has_no_current_window_only_history() {
    let mut rng = ChaCha8Rng::seed_from_u64(14);
    let w = world(40, &mut rng);
    let peers: Peers = [(7u32, peer_history(&w, &mut rng))].into_iter().collect();
    let mut frame = our_frame(&w, &(5..35).collect::<Vec<_>>(), &mut rng);
    // A minute after the peer's last frame: its window is history now.
    frame.t_s = 62.0;
    let mut coop = Cooperation::new(options(), builtin_vocabulary(), 460.0);
    coop.match_frame(&frame, &peers, 1);
    assert_eq!(coop.stats.window_matches, 0);
    assert_eq!(coop.stats.loop_closures, 1);
}

#[test]
fn a_loop_closure_finds_the_keyframe_and_its_measurements() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let w = world(40, &mut rng);
    let mut h = peer_history(&w, &mut rng);
    // The peer has moved on: its newest frames see nothing we see.
    h.clear_recent();
    let peers: Peers = [(3u32, h)].into_iter().collect();
    let seen: Vec<usize> = (0..30).collect();
    let frame = our_frame(&w, &seen, &mut rng);
    let voc = builtin_vocabulary();
    assert!(voc.is_some());
    let mut coop = Cooperation::new(options(), voc, 460.0);
    coop.match_frame(&frame, &peers, 1);
    assert_eq!(coop.stats.loop_closures, 1);
    let key = *peers[&3].keyframes.keys().next().unwrap_or(&0);
    let linked: Vec<u64> = (1..=30u64)
        .filter(|id| {
            coop.links_of(*id)
                .iter()
                .any(|l| l.source == LinkSource::Keyframe(key))
        })
        .collect();
    assert!(linked.len() >= 20, "{} of 30 linked", linked.len());
    // The evidence for a linked track: 11 measurements from the keyframe window,
    // then nothing once they are marked used.
    let ev = coop.evidence(&linked[..1], &[], &peers);
    assert_eq!(ev.vio.len(), 1);
    assert_eq!(ev.vio[0].peer_obs.len(), 11);
    assert_eq!(ev.participants.len(), 1);
    assert!(ev.historical[0]);
    coop.mark_used(&ev, &[linked[0]], &[], &[]);
    let again = coop.evidence(&linked[..1], &[], &peers);
    assert!(again.vio.is_empty());
    // The link is used up (its window is whole): forgotten at the frame's
    // end, while the other tracks' links to the window stay.
    assert!(peers[&3].keyframes[&key].is_whole());
    coop.retain_tracks(|_| true, &peers);
    assert!(coop.links_of(linked[0]).is_empty());
    assert!(!coop.links_of(linked[1]).is_empty());
    let after = coop.evidence(&linked[..2], &[], &peers);
    assert_eq!(after.vio.len(), 1);
    assert_eq!(after.vio[0].id, linked[1]);
}

/// A world of 40 landmarks and our frame seeing 30 of them, with our
/// camera's pose (what measuring a peer's frame needs).
fn world_and_posed_frame(rng: &mut ChaCha8Rng) -> (World, FrameFeatures) {
    let w = world(40, rng);
    let seen: Vec<usize> = (0..30).collect();
    let mut frame = our_frame(&w, &seen, rng);
    frame.camera = Some(CameraEstimate {
        rot: forward(),
        pos: Vector3::new(0.8, -0.3, 0.0),
        cov: nalgebra::SMatrix::<f64, 6, 6>::identity() * 1e-6,
    });
    frame.sigma_normalized = 1.0 / 460.0;
    (w, frame)
}

#[test]
fn a_peer_started_again_in_a_new_frame_is_aligned_anew() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let (w, mut frame) = world_and_posed_frame(&mut rng);
    // Fixed alignments (no estimator here to hold the frames in its state).
    let opts = CooperationOptions {
        align_peer_frames: true,
        alignment_confirmations: 1,
        peer_frame_state_s: Some(0.0),
        ..options()
    };
    let mut coop = Cooperation::new(opts, builtin_vocabulary(), 460.0);
    let in_frame = |epoch: u64, rng: &mut ChaCha8Rng| -> Peers {
        let mut h = peer_history_in(&w, rng, epoch);
        h.clear_recent();
        [(3u32, h)].into_iter().collect()
    };
    let before = in_frame(5, &mut rng);
    coop.match_frame(&frame, &before, 1);
    assert!(coop
        .frame_of(3, 5)
        .is_some_and(|a| matches!(a, super::FrameUse::Fused(_))));
    let linked: Vec<u64> = (1..=30u64)
        .filter(|id| !coop.links_of(*id).is_empty())
        .collect();
    assert!(linked.len() >= 20, "{} of 30 linked", linked.len());
    assert_eq!(coop.evidence(&linked[..1], &[], &before).vio.len(), 1);
    // The peer started again: the same window now says it is in frame 6,
    // which we know nothing of yet, so it is not used ...
    let after = in_frame(6, &mut rng);
    assert!(coop.frame_of(3, 6).is_none());
    assert!(coop.evidence(&linked[..1], &[], &after).vio.is_empty());
    // ... until a loop closure to it aligns that frame too, a second later
    // (the old one is kept for the windows of before).
    frame.t_s += 1.0;
    coop.match_frame(&frame, &after, 2);
    assert!(coop
        .frame_of(3, 6)
        .is_some_and(|a| matches!(a, super::FrameUse::Fused(_))));
    assert!(coop
        .frame_of(3, 5)
        .is_some_and(|a| matches!(a, super::FrameUse::Fused(_))));
    assert_eq!(coop.evidence(&linked[..1], &[], &after).vio.len(), 1);
    let frames = coop.peer_frames();
    assert_eq!(frames[&3].keys().copied().collect::<Vec<_>>(), vec![5, 6]);
    for f in frames[&3].values() {
        let a = f.alignment().expect("aligned");
        assert!(a.yaw_rad.abs() < 0.01, "yaw {}", a.yaw_rad);
        assert!(a.t_m.norm() < 0.05, "t {:?}", a.t_m);
    }
}

/// Peer frames aligned on one confirmation and held by the state for 60 s.
fn held_frame_options() -> CooperationOptions {
    CooperationOptions {
        align_peer_frames: true,
        peer_frame_state_s: Some(60.0),
        alignment_confirmations: 1,
        ..options()
    }
}

/// With `peer_frame_state_s` a confirmed frame is handed to the estimator
/// (a seed), its windows wait for the state to hold it, are then taken into
/// our frame at the state's mean with their Jacobian w.r.t. it, and further
/// loop closures do not measure it, until the state lets it go: a fixed
/// alignment then, refined by them.
#[test]
fn a_frame_for_the_state_is_seeded_once_and_used_at_the_states_mean() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let (w, mut frame) = world_and_posed_frame(&mut rng);
    let mut coop = Cooperation::new(held_frame_options(), builtin_vocabulary(), 460.0);
    let mut h = peer_history_in(&w, &mut rng, 5);
    h.clear_recent();
    let peers: Peers = [(3u32, h)].into_iter().collect();
    coop.match_frame(&frame, &peers, 4);
    let seeds = coop.take_frame_seeds();
    assert_eq!(seeds.len(), 1);
    assert_eq!((seeds[0].peer, seeds[0].epoch, seeds[0].clone), (3, 5, 4));
    assert!(seeds[0].measurement.alignment.yaw_rad.abs() < 0.01);
    assert!(coop.take_frame_seeds().is_empty(), "taken once");
    assert!(coop.keeps_frame(3, 5) && !coop.keeps_frame(3, 6));
    let linked: Vec<u64> = (1..=30u64)
        .filter(|id| !coop.links_of(*id).is_empty())
        .collect();
    assert!(!linked.is_empty());
    // Not in the state yet: not used.
    assert!(coop.frame_of(3, 5).is_none());
    assert!(coop.evidence(&linked[..1], &[], &peers).vio.is_empty());
    let held = crate::estimator::frame_alignment::FrameAlignment {
        yaw_rad: 0.001,
        t_m: Vector3::new(0.01, 0.0, 0.0),
        cov: nalgebra::Matrix4::identity() * 1e-4,
    };
    coop.set_state_frames([((3, 5), held)].into_iter().collect());
    assert!(matches!(
        coop.frame_of(3, 5),
        Some(super::FrameUse::InState(..))
    ));
    let ev = coop.evidence(&linked[..1], &[], &peers);
    assert_eq!(ev.vio.len(), 1);
    let link = ev.participants[0]
        .frame
        .as_ref()
        .expect("the frame's Jacobians");
    assert_eq!(link.at.yaw_rad, 0.001);
    assert_eq!(coop.peer_frames()[&3][&5].alignment(), Some(&held));
    assert!(coop.peer_frames()[&3][&5].in_filter);
    // Held by the state: a later loop closure measures it no more.
    let measured = coop.peer_frames()[&3][&5].measurements;
    frame.t_s += 2.0;
    coop.match_frame(&frame, &peers, 5);
    assert_eq!(coop.peer_frames()[&3][&5].measurements, measured);
    assert!(coop.take_frame_seeds().is_empty());
    // Let go: a fixed alignment, used through its covariance and refined.
    let confirmed_at = frame.t_s - 2.0;
    assert!(coop
        .frame_aligned_at(3, 5)
        .is_some_and(|t| (t - confirmed_at).abs() < 1e-9));
    coop.freeze_frame(3, 5, held);
    coop.set_state_frames(BTreeMap::new());
    assert!(matches!(coop.frame_of(3, 5), Some(super::FrameUse::Fused(a)) if a == held));
    assert!(!coop.peer_frames()[&3][&5].in_filter);
    frame.t_s += 2.0;
    coop.match_frame(&frame, &peers, 6);
    assert_eq!(coop.peer_frames()[&3][&5].measurements, measured + 1);
    assert!(coop.take_frame_seeds().is_empty());
}

/// Held frames share `held_frame_measurements_per_s`: with two held, each is
/// measured again at most once per `max(period, 2 / rate)`.
#[test]
fn held_frames_share_the_measurement_rate() {
    for (rate, wait_s) in [(f64::INFINITY, 2.0), (0.25, 8.0)] {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let (w, mut frame) = world_and_posed_frame(&mut rng);
        let opts = CooperationOptions {
            held_frame_measurement_period_s: 2.0,
            held_frame_measurements_per_s: rate,
            ..held_frame_options()
        };
        let mut coop = Cooperation::new(opts, builtin_vocabulary(), 460.0);
        let peers: Peers = [3u32, 4]
            .into_iter()
            .map(|peer| {
                let mut h = peer_history_in(&w, &mut rng, 5);
                h.clear_recent();
                (peer, h)
            })
            .collect();
        coop.match_frame(&frame, &peers, 4);
        assert_eq!(coop.take_frame_seeds().len(), 2, "both frames confirmed");
        let held = crate::estimator::frame_alignment::FrameAlignment {
            yaw_rad: 0.0,
            t_m: Vector3::zeros(),
            cov: nalgebra::Matrix4::identity() * 1e-4,
        };
        coop.set_state_frames([((3, 5), held), ((4, 5), held)].into_iter().collect());
        let t0 = frame.t_s;
        let mut measured: BTreeMap<u32, Vec<f64>> = BTreeMap::new();
        for step in 1..=40u64 {
            frame.t_s = t0 + 0.5 * step as f64;
            coop.match_frame(&frame, &peers, 4 + step);
            for m in coop.take_held_frame_measurements() {
                measured.entry(m.peer).or_default().push(frame.t_s - t0);
            }
        }
        for peer in [3, 4] {
            let times = &measured[&peer];
            assert!(times.len() >= 2, "rate {rate}, peer {peer}: {times:?}");
            let mut last = 0.0;
            for &t in times {
                assert!(
                    t - last >= wait_s - 1e-9,
                    "rate {rate}, peer {peer}: {times:?}"
                );
                last = t;
            }
            assert!(
                times[0] < wait_s + 1.0,
                "measured as soon as allowed: {times:?}"
            );
        }
    }
}

#[test]
fn a_frame_of_another_place_makes_no_link() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let w = world(40, &mut rng);
    let other = world(40, &mut rng);
    let peers: Peers = [(1u32, peer_history(&w, &mut rng))].into_iter().collect();
    let frame = our_frame(&other, &(0..30).collect::<Vec<_>>(), &mut rng);
    let mut coop = Cooperation::new(options(), builtin_vocabulary(), 460.0);
    coop.match_frame(&frame, &peers, 1);
    assert_eq!(coop.stats.links, 0);
    assert_eq!(coop.stats.loop_closures, 0);
}

#[test]
fn many_peers_are_matched_in_turn_and_all_within_a_few_frames() {
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let w = world(40, &mut rng);
    // Seven peers flew the same window; a frame matches three of them.
    let peers: Peers = (1..=7u32)
        .map(|p| (p, peer_history(&w, &mut rng)))
        .collect();
    let frame = our_frame(&w, &(5..35).collect::<Vec<_>>(), &mut rng);
    let mut coop = Cooperation::new(options(), None, 460.0);
    coop.match_frame(&frame, &peers, 1);
    assert_eq!(coop.stats.window_matches, 3);
    for seq in 2..=3 {
        coop.match_frame(&frame, &peers, seq);
    }
    let linked: BTreeSet<u32> = (1..=30u64)
        .flat_map(|id| coop.links_of(id).iter().map(|l| l.peer).collect::<Vec<_>>())
        .collect();
    assert_eq!(
        linked.len(),
        7,
        "peers linked after three frames: {linked:?}"
    );
}

#[test]
fn a_frames_update_takes_at_most_the_busiest_participants() {
    let mut rng = ChaCha8Rng::seed_from_u64(16);
    let w = world(40, &mut rng);
    let peers: Peers = (1..=5u32)
        .map(|p| (p, peer_history(&w, &mut rng)))
        .collect();
    let frame = our_frame(&w, &(5..35).collect::<Vec<_>>(), &mut rng);
    let opts = CooperationOptions {
        max_peers_matched_per_frame: 5,
        max_peers_per_track: 5,
        max_ci_participants: 2,
        ..options()
    };
    let mut coop = Cooperation::new(opts, None, 460.0);
    coop.match_frame(&frame, &peers, 1);
    let ids: Vec<u64> = (1..=30).collect();
    let ev = coop.evidence(&ids, &[], &peers);
    assert_eq!(ev.participants.len(), 2);
    assert!(!ev.vio.is_empty());
    for t in &ev.vio {
        assert!(t.peer_obs.iter().all(|o| o.participant < 2));
    }
}

/// Keyframe snapshot `k` (frame `k`, time `k` s) of a window of one clone at the
/// origin.
fn one_clone_keyframe(k: u64) -> StateSnapshot {
    let t = k as f64;
    StateSnapshot {
        frame_index: k,
        t_s: t,
        keyframe: true,
        frame_epoch: 0,
        camera: CameraModelWire::default(),
        pixel_sigma_px: 1.0,
        covariance: PackedCovariance::from_dmatrix(&(DMatrix::identity(6, 6) * 1e-4))
            .unwrap_or_default(),
        clones: vec![CameraPose::new(t, &Matrix3::identity(), &Vector3::zeros())],
        landmarks: Vec::new(),
    }
}

#[test]
fn the_keyframe_database_forgets_what_the_history_bound_dropped() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let Some(voc) = builtin_vocabulary() else {
        panic!("no built-in vocabulary");
    };
    let mut db = loop_closure::KeyframeDb::new(voc);
    let mut h = PeerHistory::default();
    // Room for about 40 windows of one clone and 30 descriptors.
    let limits = HistoryLimits {
        max_bytes: 40 * 1500,
        recent_s: 2.0,
        retention: Default::default(),
    };
    let mut largest = 0;
    for k in 0..600u64 {
        let t = k as f64;
        let entries = (0..30)
            .map(|i| DescriptorEntry::new(k * 100 + i, Descriptor(rng.random())))
            .collect();
        h.add_descriptors(
            DescriptorBatch {
                frame_index: k,
                t_s: t,
                keyframe: true,
                entries,
            },
            &limits,
        );
        h.add_snapshot(one_clone_keyframe(k), &limits);
        db.index_new(&h);
        largest = largest.max(db.len());
    }
    let live = h.keyframes.len();
    assert!(
        h.dropped_keyframes > 500 && live < 100,
        "{live} live, {} dropped",
        h.dropped_keyframes
    );
    // Never more than the live windows plus what waits for the next rebuild.
    assert!(
        largest <= live + 64,
        "{largest} entries for {live} live windows"
    );
    assert!(
        db.len() >= live,
        "{} entries, {live} live windows",
        db.len()
    );
}

/// A peer's windows stored before our first frame (we started late, or were
/// restarted) are all indexed, a few per frame on top of the newest ones; an
/// old window whose descriptors never came is passed over, not waited for.
#[test]
fn windows_stored_before_we_looked_are_indexed_over_the_next_frames() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let Some(voc) = builtin_vocabulary() else {
        panic!("no built-in vocabulary");
    };
    let limits = HistoryLimits {
        max_bytes: usize::MAX,
        recent_s: 2.0,
        retention: Default::default(),
    };
    let mut h = PeerHistory::default();
    for k in 0..50u64 {
        let t = k as f64;
        // Window 10's descriptors were lost.
        if k != 10 {
            let entries = (0..30)
                .map(|i| DescriptorEntry::new(k * 100 + i, Descriptor(rng.random())))
                .collect();
            let batch = DescriptorBatch {
                frame_index: k,
                t_s: t,
                keyframe: true,
                entries,
            };
            h.add_descriptors(batch, &limits);
        }
        h.add_snapshot(one_clone_keyframe(k), &limits);
    }
    let mut db = loop_closure::KeyframeDb::new(voc);
    // The newest 4 and 8 older ones per frame: 12, 20, 28, 36, 44, then the last
    // 5 of the 49 that have descriptors.
    let mut sizes = Vec::new();
    for _ in 0..7 {
        db.index_new(&h);
        sizes.push(db.len());
    }
    assert_eq!(sizes, vec![12, 20, 28, 36, 44, 49, 49]);

    // History catch-up brings window 10 again, with its descriptors: it is
    // indexed at the next frame.
    let mut complete = h.keyframes.values().nth(10).cloned().expect("window 10");
    complete.descriptors = (0..30)
        .map(|i| DescriptorEntry::new(1000 + i, Descriptor(rng.random())))
        .collect();
    assert_eq!(
        h.add_replayed(complete, &limits),
        crate::peer_history::Replayed::Completed
    );
    db.index_new(&h);
    assert_eq!(db.len(), 50);
}
