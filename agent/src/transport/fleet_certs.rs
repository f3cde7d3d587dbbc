//! A fleet's TLS certificates for the `tls` Zenoh configuration: one certificate
//! authority (CA) and, signed by it, a key and certificate per robot or router, each
//! with its common name (what `robot_certificates` checks) and the host names or
//! addresses its peers connect to (what `verify_name_on_connect` checks).
//!
//! Files in the output folder: `ca.pem` and `ca-key.pem` (keep the key off the
//! robots), and `<name>-cert.pem` and `<name>-key.pem` per member. An existing CA in
//! the folder is reused, so robots can join later; existing member files are never
//! overwritten. Keys are ECDSA P-256, written readable by their owner only.

use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use std::path::{Path, PathBuf};
use time::{Duration, OffsetDateTime};

/// Why certificates could not be made; nothing was written when this is returned.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    /// A name, host or validity is unusable.
    #[error("{0}")]
    Invalid(String),
    /// A member's files exist already: re-issuing would silently replace a robot's
    /// identity.
    #[error("{0} exists already: remove it to issue that certificate again")]
    Exists(PathBuf),
    /// Only one of `ca.pem` and `ca-key.pem` is in the folder.
    #[error("{0} is missing beside the other CA file")]
    HalfCa(PathBuf),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        source: std::io::Error,
    },
    /// Making or parsing a key or certificate failed.
    #[error("{what}: {source}")]
    Crypto {
        /// What was being made or read.
        what: String,
        /// rcgen's error.
        source: rcgen::Error,
    },
}

/// One certificate to issue.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Member {
    /// Its common name, also its files' prefix: 1 to 64 characters of `A-Z a-z 0-9
    /// _ - .`.
    pub name: String,
    /// The DNS names and IP addresses others reach it at (subjectAltName), at least
    /// one.
    pub hosts: Vec<String>,
}

/// What to issue.
#[derive(Clone, Debug)]
pub struct Request {
    /// The CA's common name when a new CA is made.
    pub ca_name: String,
    /// Days a new CA is valid.
    pub ca_days: u32,
    /// Days each member's certificate is valid.
    pub days: u32,
    /// The certificates.
    pub members: Vec<Member>,
}

/// What was written.
#[derive(Debug)]
pub struct Issued {
    /// Whether the CA was made now (else the folder's was used).
    pub new_ca: bool,
    /// The files written, in order.
    pub files: Vec<PathBuf>,
}

/// Issues `request` into `dir` (created if missing).
pub fn issue(dir: &Path, request: &Request) -> Result<Issued, CertError> {
    validate(request)?;
    let (ca_cert, ca_key) = (dir.join("ca.pem"), dir.join("ca-key.pem"));
    let member_files: Vec<(PathBuf, PathBuf)> = (request.members.iter())
        .map(|m| {
            let file = |suffix: &str| dir.join(format!("{}-{suffix}.pem", m.name));
            (file("cert"), file("key"))
        })
        .collect();
    // Everything that could refuse is checked before anything is written.
    for (cert, key) in &member_files {
        for f in [cert, key] {
            if f.exists() {
                return Err(CertError::Exists(f.clone()));
            }
        }
    }
    let new_ca = match (ca_cert.exists(), ca_key.exists()) {
        (true, true) => false,
        (false, false) => true,
        (true, false) => return Err(CertError::HalfCa(ca_key)),
        (false, true) => return Err(CertError::HalfCa(ca_cert)),
    };
    let now = OffsetDateTime::now_utc();
    // An hour back: a robot whose clock is a little behind still accepts it.
    let not_before = now - Duration::hours(1);
    let mut files = Vec::new();
    let issuer = if new_ca {
        let key = KeyPair::generate().map_err(crypto("the CA's key"))?;
        let mut params = CertificateParams::default();
        params
            .distinguished_name
            .push(DnType::CommonName, request.ca_name.as_str());
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        params.not_before = not_before;
        params.not_after = now + Duration::days(i64::from(request.ca_days));
        let cert = params
            .self_signed(&key)
            .map_err(crypto("the CA's certificate"))?;
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        write(&ca_key, &key.serialize_pem(), true)?;
        write(&ca_cert, &cert.pem(), false)?;
        files.extend([ca_cert.clone(), ca_key.clone()]);
        Issuer::new(params, key)
    } else {
        let key_pem = std::fs::read_to_string(&ca_key).map_err(io(&ca_key))?;
        let key = KeyPair::from_pem(&key_pem).map_err(crypto("ca-key.pem"))?;
        let cert_pem = std::fs::read_to_string(&ca_cert).map_err(io(&ca_cert))?;
        Issuer::from_ca_cert_pem(&cert_pem, key).map_err(crypto("ca.pem"))?
    };
    for (m, (cert_file, key_file)) in request.members.iter().zip(&member_files) {
        let what = |part: &str| format!("{}'s {part}", m.name);
        let mut params =
            CertificateParams::new(m.hosts.clone()).map_err(|e| crypto(&what("host names"))(e))?;
        params
            .distinguished_name
            .push(DnType::CommonName, m.name.as_str());
        params.is_ca = IsCa::ExplicitNoCa;
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        // Every member both accepts links (server) and opens them (client).
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        params.not_before = not_before;
        params.not_after = now + Duration::days(i64::from(request.days));
        let key = KeyPair::generate().map_err(|e| crypto(&what("key"))(e))?;
        let cert = params
            .signed_by(&key, &issuer)
            .map_err(|e| crypto(&what("certificate"))(e))?;
        write(key_file, &key.serialize_pem(), true)?;
        write(cert_file, &cert.pem(), false)?;
        files.extend([cert_file.clone(), key_file.clone()]);
    }
    Ok(Issued { new_ca, files })
}

/// The secure Zenoh links a fleet's certificates serve: each is a built-in
/// configuration of the same name reading the same `tls:` section.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum SecureLink {
    /// TLS over TCP (built-in `tls`): gets through where only TCP does, but Zenoh
    /// 1.10's TLS link loses messages under load (eclipse-zenoh/zenoh#2557).
    #[default]
    Tls,
    /// QUIC over UDP (built-in `quic`): separate send and receive streams, no loss
    /// in the same runs.
    Quic,
}

impl SecureLink {
    /// The endpoint scheme and the built-in configuration's name.
    pub fn scheme(self) -> &'static str {
        match self {
            SecureLink::Tls => "tls",
            SecureLink::Quic => "quic",
        }
    }
}

/// Writes `<name>.json5` in `dir` for each of `names`: the built-in Zenoh
/// configuration of `link` (`tls` or `quic`) with its certificate paths pointing at
/// the CA and that member's files in `dir`, for agents run on this machine (on a
/// robot, the built-in configurations read them from `/etc/fleet-vio/tls/`).
/// Returns the files.
pub fn write_zenoh_configs(
    dir: &Path,
    names: &[String],
    link: SecureLink,
) -> Result<Vec<PathBuf>, CertError> {
    let shipped = (super::ZENOH_BUILTIN_CONFIGS.iter())
        .find(|(name, _)| *name == link.scheme())
        .map(|(_, text)| *text)
        .ok_or_else(|| {
            CertError::Invalid(format!(
                "no built-in `{}` Zenoh configuration",
                link.scheme()
            ))
        })?;
    let mut files = Vec::with_capacity(names.len());
    for name in names {
        let text = shipped
            .replace(
                "/etc/fleet-vio/tls/ca.pem",
                &dir.join("ca.pem").display().to_string(),
            )
            .replace(
                "/etc/fleet-vio/tls/robot-",
                &format!("{}/{name}-", dir.display()),
            );
        let path = dir.join(format!("{name}.json5"));
        std::fs::write(&path, text).map_err(io(&path))?;
        files.push(path);
    }
    Ok(files)
}

fn validate(request: &Request) -> Result<(), CertError> {
    let invalid = |s: String| Err(CertError::Invalid(s));
    let name_ok = |n: &str| {
        (1..=64).contains(&n.len())
            && n.chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
            && n != "ca"
    };
    if !name_ok(&request.ca_name) {
        return invalid(format!(
            "CA name {:?}: 1 to 64 of A-Z a-z 0-9 _ - .",
            request.ca_name
        ));
    }
    if request.days == 0 || request.ca_days < request.days {
        return invalid(format!(
            "validity: {} days for the certificates, {} for the CA (at least 1, and the CA \
             at least as long)",
            request.days, request.ca_days
        ));
    }
    if request.members.is_empty() {
        return invalid("no robot or router to issue a certificate for".into());
    }
    for (i, m) in request.members.iter().enumerate() {
        if !name_ok(&m.name) {
            return invalid(format!(
                "name {:?}: 1 to 64 of A-Z a-z 0-9 _ - ., not \"ca\"",
                m.name
            ));
        }
        if request.members[..i].iter().any(|o| o.name == m.name) {
            return invalid(format!("{} is asked for twice", m.name));
        }
        if m.hosts.is_empty() || m.hosts.iter().any(|h| h.trim().is_empty()) {
            return invalid(format!(
                "{}: give the host names or addresses its peers connect to (their \
                 `verify_name_on_connect` checks them)",
                m.name
            ));
        }
    }
    Ok(())
}

/// Writes `text` to a new file, owner-only when it is a `secret`.
fn write(path: &Path, text: &str, secret: bool) -> Result<(), CertError> {
    use std::io::Write;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(if secret { 0o600 } else { 0o644 });
    }
    let mut file = options.open(path).map_err(io(path))?;
    file.write_all(text.as_bytes()).map_err(io(path))
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> CertError + '_ {
    move |source| CertError::Io {
        path: path.to_owned(),
        source,
    }
}

fn crypto(what: &str) -> impl Fn(rcgen::Error) -> CertError + '_ {
    move |source| CertError::Crypto {
        what: what.to_owned(),
        source,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(names: &[&str]) -> Request {
        Request {
            ca_name: "fleet-ca".into(),
            ca_days: 30,
            days: 2,
            members: (names.iter())
                .map(|n| Member {
                    name: (*n).to_owned(),
                    hosts: vec!["127.0.0.1".into(), "localhost".into()],
                })
                .collect(),
        }
    }

    #[test]
    fn a_ca_then_more_members_signed_by_the_same_ca() -> Result<(), Box<dyn std::error::Error>> {
        let dir = tempfile::tempdir()?;
        let first = issue(dir.path(), &request(&["robot0", "robot1"]))?;
        assert!(first.new_ca);
        assert_eq!(first.files.len(), 6);
        let ca = std::fs::read_to_string(dir.path().join("ca.pem"))?;
        let later = issue(dir.path(), &request(&["robot2"]))?;
        assert!(!later.new_ca);
        assert_eq!(later.files.len(), 2);
        assert_eq!(std::fs::read_to_string(dir.path().join("ca.pem"))?, ca);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            for f in ["ca-key.pem", "robot2-key.pem"] {
                let mode = std::fs::metadata(dir.path().join(f))?.permissions().mode();
                assert_eq!(mode & 0o077, 0, "{f} is readable by others: {mode:o}");
            }
        }
        Ok(())
    }

    #[test]
    fn nothing_is_overwritten_or_half_written() -> Result<(), Box<dyn std::error::Error>> {
        let dir = tempfile::tempdir()?;
        issue(dir.path(), &request(&["robot0"]))?;
        let before = std::fs::read_dir(dir.path())?.count();
        match issue(dir.path(), &request(&["robot5", "robot0"])) {
            Err(CertError::Exists(p)) => assert!(p.ends_with("robot0-cert.pem"), "{p:?}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(
            std::fs::read_dir(dir.path())?.count(),
            before,
            "robot5 was written"
        );
        std::fs::remove_file(dir.path().join("ca-key.pem"))?;
        assert!(matches!(
            issue(dir.path(), &request(&["robot6"])),
            Err(CertError::HalfCa(_))
        ));
        Ok(())
    }

    #[test]
    fn unusable_requests_are_refused_with_the_reason() {
        let dir = std::env::temp_dir().join("fleet-certs-never-written");
        let mut no_hosts = request(&["robot0"]);
        no_hosts.members[0].hosts.clear();
        let mut short_ca = request(&["robot0"]);
        short_ca.ca_days = 1;
        for (r, why) in [
            (request(&[]), "no robot"),
            (request(&["robot 0"]), "name"),
            (request(&["ca"]), "name"),
            (request(&["r", "r"]), "twice"),
            (no_hosts, "host names"),
            (short_ca, "validity"),
        ] {
            match issue(&dir, &r) {
                Err(CertError::Invalid(e)) => assert!(e.contains(why), "{e}"),
                other => panic!("{r:?}: {other:?}"),
            }
        }
        assert!(!dir.exists());
    }

    #[test]
    fn each_link_gets_its_own_configuration_pointing_at_the_members_files(
    ) -> Result<(), Box<dyn std::error::Error>> {
        let dir = tempfile::tempdir()?;
        issue(dir.path(), &request(&["robot0"]))?;
        for link in [SecureLink::Tls, SecureLink::Quic] {
            let files = write_zenoh_configs(dir.path(), &["robot0".to_owned()], link)?;
            let settings = crate::transport::ZenohSettings {
                config: files[0].display().to_string(),
                ..Default::default()
            };
            let config = crate::transport::zenoh::load_config(&settings)?;
            let get = |key: &str| config.get_json(key).map_err(|e| e.to_string());
            let protocols = get("transport/link/protocols")?;
            assert_eq!(protocols, format!("[\"{}\"]", link.scheme()));
            let key = get("transport/link/tls/connect_private_key")?;
            let expected = dir.path().join("robot0-key.pem");
            assert!(key.contains(&*expected.display().to_string()), "{key}");
            assert!(std::fs::read_to_string(&files[0])?.contains(&format!("{}/", link.scheme())));
        }
        Ok(())
    }
}
