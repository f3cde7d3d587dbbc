//! What the transport tests and benchmarks share: certificates for a fleet over
//! mutual TLS.

/// In `dir`: a fleet CA (`ca.pem`) and, for each name, a key and certificate with
/// that common name (`<name>-key.pem`, `<name>-cert.pem`, for 127.0.0.1 and
/// localhost), and `<name>.json5`: `broker-free-config/zenoh-<link>.json5` as
/// shipped (`link` is `tls` or `quic`) with only its certificate paths changed to
/// these files; all made by `agent certs --zenoh-configs` (the binary at `agent`).
pub fn make_fleet_certificates(
    agent: &std::path::Path,
    dir: &std::path::Path,
    names: &[&str],
    link: &str,
) -> Result<(), String> {
    make(agent, dir, names, link).map_err(|e| format!("making the fleet's certificates: {e}"))
}

fn make(
    agent: &std::path::Path,
    dir: &std::path::Path,
    names: &[&str],
    link: &str,
) -> Result<(), Box<dyn std::error::Error>> {
    let mut certs = std::process::Command::new(agent);
    certs
        .args(["certs", "--zenoh-configs", "--link", link])
        .args(["--days", "2", "--out"])
        .arg(dir);
    for name in names {
        certs
            .arg("--named")
            .arg(format!("{name}=127.0.0.1,localhost"));
    }
    let made = certs.output()?;
    if !made.status.success() {
        return Err(format!("agent certs: {}", String::from_utf8_lossy(&made.stderr)).into());
    }
    Ok(())
}
