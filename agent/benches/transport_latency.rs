//! One-way latency of a 10 KB payload per transport, sender and receiver in this
//! process (one clock), the receiver blocked in `receive` as an agent is.
//!
//! `cargo bench -p agent --bench transport_latency [-- MESSAGES [RATE_HZ]]`
//! (default 2000 messages at 500 Hz, the first 100 not counted). Prints p50, p99 and
//! the maximum in microseconds for inproc, zenoh (loopback TCP) and iceoryx2.
use agent::transport::{
    open, Iceoryx2Settings, InprocHub, Transport, TransportKind, TransportSettings, ZenohSettings,
};
use common::messages::MessageKind;
use std::time::{Duration, Instant};

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
        "{:<10} {:>10} {:>10} {:>10}",
        "transport", "p50 us", "p99 us", "max us"
    );
    for kind in [
        TransportKind::Inproc,
        TransportKind::Zenoh,
        TransportKind::Iceoryx2,
    ] {
        let mut latencies = measure(kind, messages.max(WARM_UP + 1), rate_hz)?;
        latencies.sort_by(f64::total_cmp);
        let at = |q: f64| latencies[((latencies.len() - 1) as f64 * q).round() as usize];
        println!(
            "{:<10} {:>10.1} {:>10.1} {:>10.1}",
            format!("{kind:?}").to_lowercase(),
            at(0.5),
            at(0.99),
            at(1.0)
        );
    }
    Ok(())
}

/// Latencies in microseconds after the warm-up.
fn measure(kind: TransportKind, messages: usize, rate_hz: f64) -> anyhow::Result<Vec<f64>> {
    let hub = InprocHub::new();
    let ports = common::loopback_ports::free_loopback_ports(2)?;
    let fleet_id = format!("latency-{}-{}", std::process::id(), kind as u8);
    let settings = |i: usize| TransportSettings {
        fleet_id: fleet_id.clone(),
        robot_id: i as u32 + 1,
        kind,
        zenoh: ZenohSettings {
            config: "loopback".to_owned(),
            listen: vec![format!("tcp/127.0.0.1:{}", ports[i])],
            connect: vec![format!("tcp/127.0.0.1:{}", ports[1 - i])],
            robot_certificates: None,
        },
        iceoryx2: Iceoryx2Settings::default(),
    };
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
