//! What the transport tests and benchmarks share: certificates for a fleet over
//! mutual TLS.

/// In `dir`: a fleet CA (`ca.pem`) and, for each name, a key and certificate with
/// that common name (`<name>-key.pem`, `<name>-cert.pem`, for 127.0.0.1), made with
/// the `openssl` command, and `<name>.json5`: `broker-free-config/zenoh-tls.json5` as
/// shipped with only its certificate paths changed to these files.
pub fn make_fleet_certificates(dir: &std::path::Path, names: &[&str]) -> Result<(), String> {
    make(dir, names).map_err(|e| format!("making the fleet's certificates: {e}"))
}

fn make(dir: &std::path::Path, names: &[&str]) -> Result<(), Box<dyn std::error::Error>> {
    let sh = |args: &[&str]| -> Result<(), Box<dyn std::error::Error>> {
        let status = std::process::Command::new("openssl")
            .args(args)
            .current_dir(dir)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()?;
        if !status.success() {
            return Err(format!("openssl {args:?}: {status}").into());
        }
        Ok(())
    };
    let ec = [
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:prime256v1",
        "-nodes",
    ];
    sh(&[
        &["req", "-x509"][..],
        &ec,
        &["-keyout", "ca-key.pem", "-out", "ca.pem"],
        &["-days", "2", "-subj", "/CN=fleet-ca"],
    ]
    .concat())?;
    std::fs::write(
        dir.join("ext.cnf"),
        "basicConstraints=CA:FALSE\nsubjectAltName=IP:127.0.0.1,DNS:localhost\n\
         extendedKeyUsage=serverAuth,clientAuth\n",
    )?;
    let shipped = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../broker-free-config/zenoh-tls.json5"),
    )?;
    for name in names {
        let (key, csr, cert) = (
            format!("{name}-key.pem"),
            format!("{name}.csr"),
            format!("{name}-cert.pem"),
        );
        let subject = format!("/CN={name}");
        sh(&[
            &["req"][..],
            &ec,
            &["-keyout", &key, "-out", &csr, "-subj", &subject],
        ]
        .concat())?;
        sh(&[
            "x509",
            "-req",
            "-in",
            &csr,
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca-key.pem",
            "-CAcreateserial",
            "-out",
            &cert,
            "-days",
            "2",
            "-extfile",
            "ext.cnf",
        ])?;
        let config = shipped
            .replace(
                "/etc/fleet-vio/tls/ca.pem",
                &dir.join("ca.pem").display().to_string(),
            )
            .replace(
                "/etc/fleet-vio/tls/robot-",
                &format!("{}/{name}-", dir.display()),
            );
        std::fs::write(dir.join(format!("{name}.json5")), config)?;
    }
    Ok(())
}
