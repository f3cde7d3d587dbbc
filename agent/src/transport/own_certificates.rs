//! Checks an agent's own TLS files before its Zenoh session opens, so that the two
//! mistakes that otherwise fail in silence are said at start:
//!
//! - **A certificate outside its validity period.** Peers refuse the handshake, and
//!   Zenoh only logs it in its listener; the agent would run alone. Robots without a
//!   real-time clock often boot in 1970 or with yesterday's time, so a certificate
//!   "not yet valid" names this machine's clock. That is logged as an error and the
//!   agent goes on: its own estimator still runs, and Zenoh keeps retrying its
//!   `connect` endpoints, so the links come up once the clock is set (tried with
//!   libfaketime: 3 s after, deploy/README.md section 5). A
//!   certificate that expires within [`EXPIRY_WARNING_DAYS`] days is a warning.
//! - **The wrong robot's certificate.** With `robot_certificates`, peers accept robot
//!   N's messages only from the certificate named for N; an agent started with
//!   another robot's files would be refused by everyone. That is a configuration
//!   error: the agent does not start.

use super::zenoh_acl::RobotCertificates;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

/// A certificate that expires within this many days is reported at start.
pub const EXPIRY_WARNING_DAYS: i64 = 14;

/// The largest certificate file read: PEM certificates are a few KB.
const MAX_PEM_BYTES: u64 = 1 << 20;

/// The TLS section's certificate files, as Zenoh's TLS and QUIC links read them.
const CERTIFICATE_KEYS: [(&str, Role); 3] = [
    ("transport/link/tls/root_ca_certificate", Role::Authority),
    ("transport/link/tls/listen_certificate", Role::Own),
    ("transport/link/tls/connect_certificate", Role::Own),
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    /// The fleet's CA: its name is not checked.
    Authority,
    /// This robot's certificate: named for its robot id when ids are bound.
    Own,
}

/// What a certificate file says about itself.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CertificateInfo {
    /// The subject's common name, if it has one.
    pub common_name: Option<String>,
    /// Valid from, seconds since the Unix epoch.
    pub not_before_s: i64,
    /// Valid until, seconds since the Unix epoch.
    pub not_after_s: i64,
}

/// What the check found that the agent should say but that does not stop it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Finding {
    /// Peers refuse the handshake until this is fixed.
    Error(String),
    /// Fine now, not for long.
    Warning(String),
}

/// Reads the first certificate of the PEM file at `path`.
pub fn read_certificate(path: &Path) -> Result<CertificateInfo, String> {
    use std::io::Read;
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut bytes = Vec::new();
    file.take(MAX_PEM_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if bytes.len() as u64 > MAX_PEM_BYTES {
        return Err(format!(
            "{}: larger than {MAX_PEM_BYTES} bytes, not a PEM certificate",
            path.display()
        ));
    }
    let (_, pem) = x509_parser::pem::parse_x509_pem(&bytes)
        .map_err(|e| format!("{}: not a PEM certificate: {e}", path.display()))?;
    let cert = pem
        .parse_x509()
        .map_err(|e| format!("{}: not an X.509 certificate: {e}", path.display()))?;
    let validity = cert.validity();
    let common_name = (cert.subject().iter_common_name().next())
        .and_then(|cn| cn.as_str().ok())
        .map(str::to_owned);
    Ok(CertificateInfo {
        common_name,
        not_before_s: validity.not_before.timestamp(),
        not_after_s: validity.not_after.timestamp(),
    })
}

/// Checks the certificate files named in `config`'s TLS section (any that are
/// set) at time `now`. Unreadable files, and with `bind` (robot `robot_id`'s ids
/// bound to names) an own certificate named for someone else, are errors; the
/// validity period gives findings to log.
pub fn check(
    config: &zenoh::Config,
    bind: Option<(&RobotCertificates, u32)>,
    now: SystemTime,
) -> Result<Vec<Finding>, String> {
    let now_s = match now.duration_since(UNIX_EPOCH) {
        Ok(d) => d.as_secs() as i64,
        Err(e) => -(e.duration().as_secs() as i64),
    };
    let mut findings = Vec::new();
    let mut seen: Vec<(PathBuf, Role)> = Vec::new();
    for (key, role) in CERTIFICATE_KEYS {
        let Some(path) = configured_path(config, key) else {
            continue;
        };
        // Robots usually accept and open links with one certificate: say what is
        // wrong with a file once, not once per key that names it.
        if seen.contains(&(path.clone(), role)) {
            continue;
        }
        seen.push((path.clone(), role));
        let info = read_certificate(&path)?;
        if let (Role::Own, Some((certs, robot_id))) = (role, bind) {
            let expected = certs.name_of(robot_id);
            if info.common_name.as_deref() != Some(expected.as_str()) {
                return Err(format!(
                    "{} ({key}) is named {:?}, but robot {robot_id}'s certificate must be \
                     named {expected:?} (robot_certificates): peers would refuse every \
                     message this agent sends. Use robot {robot_id}'s files or fix \
                     robot_id",
                    path.display(),
                    info.common_name.as_deref().unwrap_or("(no common name)"),
                ));
            }
        }
        findings.extend(validity_finding(&path, &info, now_s));
    }
    Ok(findings)
}

/// The file path at `key`, if the configuration sets one.
fn configured_path(config: &zenoh::Config, key: &str) -> Option<PathBuf> {
    let json = config.get_json(key).ok()?;
    match serde_json::from_str::<serde_json::Value>(&json).ok()? {
        serde_json::Value::String(s) if !s.is_empty() => Some(PathBuf::from(s)),
        _ => None,
    }
}

fn validity_finding(path: &Path, info: &CertificateInfo, now_s: i64) -> Option<Finding> {
    let day = 86_400;
    if now_s < info.not_before_s {
        return Some(Finding::Error(format!(
            "{} is not valid before {}, and this machine's clock says {}: peers refuse \
             the TLS handshake until the clock is set (NTP, or a real-time clock); the \
             links come up by themselves then",
            path.display(),
            utc(info.not_before_s),
            utc(now_s)
        )));
    }
    if now_s > info.not_after_s {
        return Some(Finding::Error(format!(
            "{} expired at {} (this machine's clock says {}): peers refuse the TLS \
             handshake; issue new certificates (`agent certs`)",
            path.display(),
            utc(info.not_after_s),
            utc(now_s)
        )));
    }
    let left = (info.not_after_s - now_s) / day;
    (left < EXPIRY_WARNING_DAYS).then(|| {
        Finding::Warning(format!(
            "{} expires at {}, in {left} days: issue new certificates (`agent certs`) \
             before then",
            path.display(),
            utc(info.not_after_s)
        ))
    })
}

/// `YYYY-MM-DD hh:mm:ss UTC`, or the raw seconds if out of range.
fn utc(s: i64) -> String {
    match time::OffsetDateTime::from_unix_timestamp(s) {
        Ok(t) => format!(
            "{:04}-{:02}-{:02} {:02}:{:02}:{:02} UTC",
            t.year(),
            u8::from(t.month()),
            t.day(),
            t.hour(),
            t.minute(),
            t.second()
        ),
        Err(_) => format!("{s} s after 1970"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rcgen::{CertificateParams, DnType, KeyPair};
    use std::time::Duration;

    /// A self-signed certificate named `name`, valid from `from` to `until` days
    /// around now, written to `dir/<file>`.
    fn certificate(dir: &Path, file: &str, name: &str, from: i64, until: i64) -> PathBuf {
        let now = time::OffsetDateTime::now_utc();
        let mut params = CertificateParams::new(vec!["localhost".to_owned()]).unwrap();
        params.distinguished_name.push(DnType::CommonName, name);
        params.not_before = now + time::Duration::days(from);
        params.not_after = now + time::Duration::days(until);
        let key = KeyPair::generate().unwrap();
        let cert = params.self_signed(&key).unwrap();
        let path = dir.join(file);
        std::fs::write(&path, cert.pem()).unwrap();
        path
    }

    fn config_with(ca: &Path, own: &Path) -> zenoh::Config {
        let text = format!(
            r#"{{ transport: {{ link: {{ tls: {{ root_ca_certificate: "{}",
                 listen_certificate: "{}", connect_certificate: "{}" }} }} }} }}"#,
            ca.display(),
            own.display(),
            own.display()
        );
        zenoh::Config::from_json5(&text).unwrap()
    }

    fn bound() -> RobotCertificates {
        RobotCertificates {
            robots: vec![1, 2],
            common_name: "robot{id}".to_owned(),
            trusted_routers: Vec::new(),
        }
    }

    #[test]
    fn valid_files_of_the_right_robot_pass_quietly() {
        let dir = tempfile::tempdir().unwrap();
        let ca = certificate(dir.path(), "ca.pem", "fleet-ca", -1, 3650);
        let own = certificate(dir.path(), "robot1-cert.pem", "robot1", -1, 365);
        let certs = bound();
        let found = check(
            &config_with(&ca, &own),
            Some((&certs, 1)),
            SystemTime::now(),
        );
        assert_eq!(found, Ok(Vec::new()));
    }

    #[test]
    fn another_robots_certificate_is_refused_with_both_names() {
        let dir = tempfile::tempdir().unwrap();
        let ca = certificate(dir.path(), "ca.pem", "fleet-ca", -1, 3650);
        let own = certificate(dir.path(), "robot2-cert.pem", "robot2", -1, 365);
        let certs = bound();
        let config = config_with(&ca, &own);
        let e = check(&config, Some((&certs, 1)), SystemTime::now()).unwrap_err();
        assert!(e.contains("\"robot2\"") && e.contains("\"robot1\""), "{e}");
        // Without bound ids any name will do.
        assert_eq!(check(&config, None, SystemTime::now()), Ok(Vec::new()));
    }

    #[test]
    fn a_clock_before_the_validity_names_the_clock() {
        let dir = tempfile::tempdir().unwrap();
        let ca = certificate(dir.path(), "ca.pem", "fleet-ca", -1, 3650);
        let own = certificate(dir.path(), "robot1-cert.pem", "robot1", -1, 365);
        // A robot that booted in 1970.
        let found = check(&config_with(&ca, &own), None, UNIX_EPOCH).unwrap();
        // The CA, and the robot's file once though two keys name it.
        assert_eq!(found.len(), 2, "{found:?}");
        for f in &found {
            match f {
                Finding::Error(e) => {
                    assert!(e.contains("1970-01-01 00:00:00 UTC") && e.contains("clock"))
                }
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn expired_and_soon_expiring_certificates_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let ca = certificate(dir.path(), "ca.pem", "fleet-ca", -1, 3650);
        let soon = certificate(dir.path(), "soon.pem", "robot1", -30, 5);
        let found = check(&config_with(&ca, &soon), None, SystemTime::now()).unwrap();
        assert_eq!(found.len(), 1, "{found:?}");
        assert!(
            matches!(&found[0], Finding::Warning(w) if w.contains("in 4 days") || w.contains("in 5 days"))
        );
        let later = SystemTime::now() + Duration::from_secs(10 * 86_400);
        let found = check(&config_with(&ca, &soon), None, later).unwrap();
        assert!(
            matches!(&found[0], Finding::Error(e) if e.contains("expired")),
            "{found:?}"
        );
    }

    #[test]
    fn unreadable_or_foreign_files_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let ca = certificate(dir.path(), "ca.pem", "fleet-ca", -1, 3650);
        let missing = dir.path().join("missing.pem");
        let e = check(&config_with(&ca, &missing), None, SystemTime::now()).unwrap_err();
        assert!(e.contains("missing.pem"), "{e}");
        let garbage = dir.path().join("garbage.pem");
        std::fs::write(&garbage, "not a certificate").unwrap();
        let e = check(&config_with(&ca, &garbage), None, SystemTime::now()).unwrap_err();
        assert!(e.contains("garbage.pem") && e.contains("PEM"), "{e}");
    }

    #[test]
    fn a_configuration_without_tls_files_has_nothing_to_check() {
        let config = zenoh::Config::default();
        assert_eq!(check(&config, None, SystemTime::now()), Ok(Vec::new()));
    }
}
