//! Free ports on 127.0.0.1, for TCP and UDP alike (`tcp/`, `tls/` and `quic/`
//! endpoints), for Zenoh peers that must know each other's
//! listen address before they start (the fleet launcher, tests, benches).
//!
//! Why not bind port 0 and release it: the kernel hands out port-0 binds and the
//! source ports of outgoing connections from the same ephemeral range, so between
//! our release and the session's bind another connection (a Zenoh peer dialing out
//! in a parallel test, say) can take the port, and the bind fails with "address
//! already in use". Ports outside the ephemeral range (from 20000 up) are never
//! chosen by the kernel; we take them there, check each by binding it, and never hand the same port out
//! twice in one process.

use std::collections::BTreeSet;
use std::net::{TcpListener, UdpSocket};
use std::sync::Mutex;

/// Where Linux keeps the ephemeral range.
const EPHEMERAL_RANGE_FILE: &str = "/proc/sys/net/ipv4/ip_local_port_range";
/// Linux's default ephemeral range, used when the file cannot be read.
const DEFAULT_EPHEMERAL: (u16, u16) = (32768, 60999);
/// The lowest port we hand out: well above the registered services people run.
const LOWEST: u16 = 20000;

/// Ports handed out so far by this process: never handed out again, since the
/// session meant to bind one may not have done so yet.
static HANDED_OUT: Mutex<BTreeSet<u16>> = Mutex::new(BTreeSet::new());

/// `n` distinct loopback ports, each free when checked and outside the kernel's
/// ephemeral range when that range leaves room; otherwise ports the kernel picks.
pub fn free_loopback_ports(n: usize) -> std::io::Result<Vec<u16>> {
    let (low, high) = ephemeral_range();
    let pool = outside(low, high);
    if pool.len() < n.saturating_mul(4).max(64) {
        return kernel_ports(n);
    }
    let mut handed = HANDED_OUT
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    // Start at an offset of this process's own so that two launchers started
    // together rarely probe the same ports.
    let start = (std::process::id() as usize).wrapping_mul(7919) + handed.len();
    let mut held = Vec::with_capacity(n);
    let mut ports = Vec::with_capacity(n);
    for k in 0..pool.len() {
        if ports.len() == n {
            break;
        }
        let port = pool.at((start + k) % pool.len());
        if handed.contains(&port) {
            continue;
        }
        // Free for both protocols, so the caller may listen with either.
        if let (Ok(listener), Ok(socket)) = (
            TcpListener::bind(("127.0.0.1", port)),
            UdpSocket::bind(("127.0.0.1", port)),
        ) {
            held.push((listener, socket));
            ports.push(port);
        }
    }
    handed.extend(&ports);
    if ports.len() < n {
        return kernel_ports(n);
    }
    Ok(ports)
}

/// The kernel's ephemeral range, `(low, high)` inclusive.
fn ephemeral_range() -> (u16, u16) {
    std::fs::read_to_string(EPHEMERAL_RANGE_FILE)
        .ok()
        .and_then(|text| {
            let mut it = text.split_whitespace().map(str::parse::<u16>);
            match (it.next(), it.next()) {
                (Some(Ok(low)), Some(Ok(high))) if low <= high => Some((low, high)),
                _ => None,
            }
        })
        .unwrap_or(DEFAULT_EPHEMERAL)
}

/// Ports from `LOWEST` up, skipping the ephemeral range `[low, high]`.
struct Pool {
    below: std::ops::Range<u32>,
    above: std::ops::Range<u32>,
}

impl Pool {
    fn len(&self) -> usize {
        self.below.len() + self.above.len()
    }

    fn at(&self, i: usize) -> u16 {
        let p = if i < self.below.len() {
            self.below.start + i as u32
        } else {
            self.above.start + (i - self.below.len()) as u32
        };
        p as u16
    }
}

fn outside(low: u16, high: u16) -> Pool {
    let lowest = u32::from(LOWEST);
    Pool {
        below: lowest..u32::from(low).max(lowest),
        above: (u32::from(high) + 1).max(lowest)..65536,
    }
}

/// Ports bound together on port 0 and released: distinct, but from the ephemeral
/// range (the fallback when the range leaves no room outside it).
fn kernel_ports(n: usize) -> std::io::Result<Vec<u16>> {
    let listeners = (0..n)
        .map(|_| TcpListener::bind("127.0.0.1:0"))
        .collect::<std::io::Result<Vec<_>>>()?;
    listeners
        .iter()
        .map(|l| Ok(l.local_addr()?.port()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ports_are_distinct_free_and_outside_the_ephemeral_range() -> std::io::Result<()> {
        let (low, high) = ephemeral_range();
        let a = free_loopback_ports(5)?;
        let b = free_loopback_ports(5)?;
        let all: std::collections::BTreeSet<u16> = a.iter().chain(&b).copied().collect();
        assert_eq!(all.len(), 10, "{a:?} {b:?}");
        if outside(low, high).len() >= 64 {
            assert!(all.iter().all(|p| *p < low || *p > high), "{all:?}");
        }
        for p in all {
            drop(TcpListener::bind(("127.0.0.1", p))?);
            drop(UdpSocket::bind(("127.0.0.1", p))?);
        }
        Ok(())
    }

    #[test]
    fn the_pool_skips_the_ephemeral_range() {
        let pool = outside(32768, 60999);
        assert_eq!(pool.at(0), LOWEST);
        assert_eq!(pool.at(pool.below.len() - 1), 32767);
        assert_eq!(pool.at(pool.below.len()), 61000);
        assert_eq!(pool.at(pool.len() - 1), 65535);
        // A range reaching down past LOWEST leaves only the ports above it.
        let pool = outside(1024, 65000);
        assert_eq!(pool.below.len(), 0);
        assert_eq!(pool.at(0), 65001);
    }
}
