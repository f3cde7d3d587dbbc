//! A status line in the agent's log every `status_period_s` of wall time: what
//! an operator watching a robot's log (or `journalctl -f`) needs to see that
//! the agent keeps up, hears its peers and holds its memory bound, without
//! opening the MCAP log.

use common::metrics::percentile_sorted;
use std::fmt;

/// What the agent's counters say at one moment (cumulative since the start).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Counters {
    /// Wall seconds since the agent started.
    pub wall_s: f64,
    /// Fleet time, s (`None`: before the first tick).
    pub fleet_s: Option<f64>,
    /// Camera frames the estimator has output.
    pub frames: usize,
    /// Peers heard from lately.
    pub peers_alive: usize,
    /// Keyframe windows held of all peers.
    pub windows: usize,
    /// Bytes of those histories.
    pub history_bytes: usize,
    /// Bytes sent.
    pub sent_bytes: u64,
    /// Bytes received and accepted.
    pub received_bytes: u64,
    /// Messages refused or dropped (every reason).
    pub dropped: u64,
    /// Sensor data and frames rejected.
    pub rejected: usize,
    /// Real time: how far behind the wall clock, s (0 in lockstep).
    pub lag_s: f64,
    /// One-way latencies sampled so far (received messages).
    pub latency_samples: usize,
}

/// One status line: the counters and what changed over the period.
#[derive(Clone, Debug, PartialEq)]
pub struct Status {
    /// The counters now.
    pub now: Counters,
    /// Wall seconds the period lasted.
    pub period_s: f64,
    /// Frames output in the period.
    pub frames: usize,
    /// Mean thread CPU time of those frames, ms.
    pub cpu_ms_mean: f64,
    /// Their largest, ms.
    pub cpu_ms_max: f64,
    /// Sent in the period, KB/s.
    pub sent_kb_s: f64,
    /// Received in the period, KB/s.
    pub received_kb_s: f64,
    /// Dropped in the period.
    pub dropped: u64,
    /// One-way latency of the period's messages, ms: 99th percentile and
    /// largest (`None`: none sampled).
    pub latency_ms: Option<(f64, f64)>,
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = &self.now;
        match n.fleet_s {
            Some(t) => write!(f, "fleet {t:.1} s")?,
            None => write!(f, "not started")?,
        }
        write!(
            f,
            ", {} frames in {:.0} s ({:.2} ms mean, {:.2} max), lag {:.3} s, {} peers, \
             {} windows held ({:.1} MB), sent {:.1} KB/s, received {:.1} KB/s, {} dropped, \
             {} rejected in all, latency p99 {} ms (max {})",
            self.frames,
            self.period_s,
            self.cpu_ms_mean,
            self.cpu_ms_max,
            n.lag_s,
            n.peers_alive,
            n.windows,
            n.history_bytes as f64 / 1e6,
            self.sent_kb_s,
            self.received_kb_s,
            self.dropped,
            n.rejected,
            self.latency_ms
                .map_or_else(|| "-".to_string(), |(p99, _)| format!("{p99:.1}")),
            self.latency_ms
                .map_or_else(|| "-".to_string(), |(_, max)| format!("{max:.1}")),
        )
    }
}

/// When the next status line is due, and the counters of the last one.
#[derive(Clone, Debug)]
pub struct StatusLog {
    period_s: f64,
    last: Counters,
}

impl StatusLog {
    /// A line every `period_s` wall seconds (`None` when 0 or not finite:
    /// no status lines).
    pub fn new(period_s: f64) -> Option<Self> {
        (period_s.is_finite() && period_s > 0.0).then_some(Self {
            period_s,
            last: Counters::default(),
        })
    }

    /// The status line, if one is due at `wall_s` (seconds since the agent
    /// started): `counters` are read only then; `cpu_ms(k)` is the thread CPU
    /// time of frame `k` (the period's frames are the ones output since the
    /// last line); `latencies_ms` are the latencies sampled so far (the
    /// period's are the ones after the last line's count).
    pub fn due(
        &mut self,
        wall_s: f64,
        counters: impl FnOnce() -> Counters,
        cpu_ms: impl Fn(usize) -> f64,
        latencies_ms: &[f64],
    ) -> Option<Status> {
        let period_s = wall_s - self.last.wall_s;
        if period_s < self.period_s {
            return None;
        }
        let now = Counters {
            wall_s,
            ..counters()
        };
        let last = std::mem::replace(&mut self.last, now);
        let new = last.frames.min(now.frames)..now.frames;
        let frames = new.len();
        let (mut sum, mut max) = (0.0, 0.0f64);
        for k in new {
            let c = cpu_ms(k);
            sum += c;
            max = max.max(c);
        }
        let rate = |now: u64, then: u64| now.saturating_sub(then) as f64 / 1e3 / period_s;
        let mut lat: Vec<f64> = latencies_ms
            .get(last.latency_samples.min(latencies_ms.len())..)
            .unwrap_or_default()
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .collect();
        lat.sort_unstable_by(f64::total_cmp);
        let latency_ms = percentile_sorted(&lat, 0.99).zip(lat.last().copied());
        Some(Status {
            now,
            period_s,
            frames,
            cpu_ms_mean: if frames > 0 { sum / frames as f64 } else { 0.0 },
            cpu_ms_max: max,
            sent_kb_s: rate(now.sent_bytes, last.sent_bytes),
            received_kb_s: rate(now.received_bytes, last.received_bytes),
            dropped: now.dropped.saturating_sub(last.dropped),
            latency_ms,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_comes_each_period_with_what_changed_in_it() {
        let mut log = StatusLog::new(10.0).unwrap();
        let cpu = |k: usize| if k < 100 { 1.0 } else { 3.0 };
        let at = |wall_s: f64, frames: usize, sent: u64| Counters {
            wall_s,
            fleet_s: Some(wall_s + 100.0),
            frames,
            sent_bytes: sent,
            dropped: frames as u64 / 50,
            latency_samples: frames.min(300),
            ..Counters::default()
        };
        let lat: Vec<f64> = (0..300)
            .map(|k| if k < 100 { 1.0 } else { f64::from(k) })
            .collect();
        let mut due = |c: Counters| log.due(c.wall_s, || c, cpu, &lat[..c.latency_samples]);
        assert!(due(at(9.9, 99, 0)).is_none());
        let first = due(at(10.0, 100, 50_000)).unwrap();
        assert_eq!(
            (first.frames, first.cpu_ms_mean, first.cpu_ms_max),
            (100, 1.0, 1.0)
        );
        assert!((first.sent_kb_s - 5.0).abs() < 1e-12);
        assert_eq!(first.dropped, 2);
        assert_eq!(first.latency_ms, Some((1.0, 1.0)));
        assert!(due(at(15.0, 150, 60_000)).is_none());
        let second = due(at(20.0, 200, 150_000)).unwrap();
        assert_eq!(
            (second.frames, second.cpu_ms_mean, second.cpu_ms_max),
            (100, 3.0, 3.0)
        );
        assert!((second.sent_kb_s - 10.0).abs() < 1e-12);
        // Samples 100..200 of the second period: 100..199 ms; p99 is the 99th.
        assert_eq!(second.latency_ms, Some((198.0, 199.0)));
        assert!(second
            .to_string()
            .ends_with("latency p99 198.0 ms (max 199.0)"));
        let line = second.to_string();
        assert!(
            line.starts_with("fleet 120.0 s, 100 frames in 10 s (3.00 ms mean"),
            "{line}"
        );
    }

    #[test]
    fn a_zero_period_means_no_status_lines() {
        assert!(StatusLog::new(0.0).is_none());
        assert!(StatusLog::new(f64::NAN).is_none());
        assert!(StatusLog::new(-1.0).is_none());
    }
}
