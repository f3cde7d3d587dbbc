//! One-way latency of a 10 KB payload per transport, sender and receiver in this
//! process (one clock), the receiver blocked in `receive` as an agent is.
//!
//! `cargo bench -p agent --bench transport_latency [-- MESSAGES [RATE_HZ]]`
//! (default 2000 messages at 500 Hz, the first 100 not counted). Prints p50, p99 and
//! the maximum in microseconds for inproc, zenoh (loopback TCP), zenoh over mutual TLS
//! and over QUIC, each without and with robot ids bound to the certificates
//! (`robot_certificates`, Zenoh access control; certificates made by `agent certs`),
//! and iceoryx2.
use agent::transport::zenoh_acl::RobotCertificates;
use agent::transport::{
    open, Iceoryx2Settings, InprocHub, Transport, TransportKind, TransportSettings, ZenohSettings,
};
use common::messages::MessageKind;
use std::time::{Duration, Instant};

#[path = "../tests/support/mod.rs"]
mod support;

const PAYLOAD: usize = 10_000;
const WARM_UP: usize = 100;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let messages: usize = args.first().and_then(|a| a.parse().ok()).unwrap_or(2000);
    let rate_hz: f64 = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(500.0);
    println!("one-way latency, {PAYLOAD} B payload, {messages} messages at {rate_hz} Hz");
    println!(
        "{:<14} {:>10} {:>10} {:>10}",
        "transport", "p50 us", "p99 us", "max us"
    );
    let mut setups = vec![
        Setup::plain(TransportKind::Inproc),
        Setup::plain(TransportKind::Zenoh),
    ];
    // One folder of certificates and configurations per secure link.
    let mut folders = Vec::new();
    for link in ["tls", "quic"] {
        let certificates = tempfile::tempdir()?;
        match support::make_fleet_certificates(
            std::path::Path::new(env!("CARGO_BIN_EXE_agent")),
            certificates.path(),
            &["robot1", "robot2"],
            link,
        ) {
            Ok(()) => {
                setups.push(Setup::secure(link, certificates.path(), false));
                setups.push(Setup::secure(link, certificates.path(), true));
                folders.push(certificates);
            }
            Err(e) => eprintln!("no {link} rows: {e}"),
        }
    }
    setups.push(Setup::plain(TransportKind::Iceoryx2));
    for (n, setup) in setups.iter().enumerate() {
        let mut latencies = measure(setup, n, messages.max(WARM_UP + 1), rate_hz)?;
        latencies.sort_by(f64::total_cmp);
        let at = |q: f64| latencies[((latencies.len() - 1) as f64 * q).round() as usize];
        println!(
            "{:<14} {:>10.1} {:>10.1} {:>10.1}",
            setup.label,
            at(0.5),
            at(0.99),
            at(1.0)
        );
    }
    Ok(())
}

/// One row: a transport and, for Zenoh, the configuration file, the endpoints'
/// scheme and the id binding.
struct Setup {
    label: String,
    kind: TransportKind,
    /// `None`: the built-in `loopback` over TCP; else the secure link's scheme and
    /// the folder of its files.
    secure: Option<(&'static str, std::path::PathBuf)>,
    bind_ids: bool,
}

impl Setup {
    fn plain(kind: TransportKind) -> Self {
        let label = format!("{kind:?}").to_lowercase();
        Self {
            label,
            kind,
            secure: None,
            bind_ids: false,
        }
    }

    fn secure(link: &'static str, dir: &std::path::Path, bind_ids: bool) -> Self {
        Self {
            label: format!("zenoh-{link}{}", if bind_ids { "+ids" } else { "" }),
            kind: TransportKind::Zenoh,
            secure: Some((link, dir.to_owned())),
            bind_ids,
        }
    }

    /// Endpoint `i` (robot `i + 1`) of two, on `ports`.
    fn settings(&self, fleet_id: &str, ports: &[u16], i: usize) -> TransportSettings {
        let scheme = self.secure.as_ref().map_or("tcp", |(link, _)| *link);
        let endpoint = |p: u16| format!("{scheme}/127.0.0.1:{p}");
        let config = match &self.secure {
            Some((_, dir)) => dir
                .join(format!("robot{}.json5", i + 1))
                .display()
                .to_string(),
            None => "loopback".to_owned(),
        };
        TransportSettings {
            fleet_id: fleet_id.to_owned(),
            robot_id: i as u32 + 1,
            kind: self.kind,
            zenoh: ZenohSettings {
                config,
                listen: vec![endpoint(ports[i])],
                connect: vec![endpoint(ports[1 - i])],
                robot_certificates: self.bind_ids.then(|| RobotCertificates {
                    robots: vec![1, 2],
                    common_name: "robot{id}".to_owned(),
                    trusted_routers: Vec::new(),
                }),
            },
            iceoryx2: Iceoryx2Settings::default(),
        }
    }
}

/// Latencies in microseconds after the warm-up; `n` tells the rows' fleets apart.
fn measure(setup: &Setup, n: usize, messages: usize, rate_hz: f64) -> anyhow::Result<Vec<f64>> {
    let hub = InprocHub::new();
    let ports = common::loopback_ports::free_loopback_ports(2)?;
    let fleet_id = format!("latency-{}-{n}", std::process::id());
    let settings = |i: usize| setup.settings(&fleet_id, &ports, i);
    let mut sender = open(&settings(0), Some(&hub))?;
    let mut receiver = open(&settings(1), Some(&hub))?;
    wait_for_peer(sender.as_mut())?;
    wait_for_peer(receiver.as_mut())?;

    let epoch = Instant::now();
    let receiving = std::thread::spawn(move || -> anyhow::Result<Vec<f64>> {
        let mut latencies = Vec::with_capacity(messages);
        while latencies.len() < messages {
            let Some(m) = receiver.receive(Duration::from_secs(10))? else {
                anyhow::bail!("message {} of {messages} did not arrive", latencies.len());
            };
            let arrived = epoch.elapsed().as_nanos() as u64;
            let sent = u64::from_le_bytes(m.bytes[..8].try_into()?);
            latencies.push(arrived.saturating_sub(sent) as f64 / 1e3);
        }
        receiver.close(Duration::from_secs(5))?;
        Ok(latencies)
    });
    let period = Duration::from_secs_f64(1.0 / rate_hz);
    let mut payload = vec![0u8; PAYLOAD];
    let start = Instant::now();
    for i in 0..messages {
        let due = start + period * i as u32;
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let now = epoch.elapsed().as_nanos() as u64;
        payload[..8].copy_from_slice(&now.to_le_bytes());
        sender.publish(MessageKind::Descriptors, &payload)?;
    }
    let latencies = receiving
        .join()
        .map_err(|_| anyhow::anyhow!("receiver panicked"))??;
    sender.close(Duration::from_secs(5))?;
    Ok(latencies[WARM_UP..].to_vec())
}

fn wait_for_peer(t: &mut dyn Transport) -> anyhow::Result<()> {
    let start = Instant::now();
    while t.presence().is_empty() {
        anyhow::ensure!(
            start.elapsed() < Duration::from_secs(10),
            "{}: no peer",
            t.name()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(())
}
