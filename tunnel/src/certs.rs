//! `uavmeta tunnel certs`: the run's CA and a host's certificate, for the tunnel's mutual TLS, made
//! with rcgen (the certificate generator Zenoh's TLS links already build on).
//!
//! In `DIR`: `ca.pem` and `ca.key` (made once, then reused to sign every later host), and
//! `NAME.pem` and `NAME.key` for host `NAME`, valid for the names and addresses given (the
//! learner host's must include the address remote hosts connect to: `join` checks it). Keys are
//! written readable by their owner only. The same files can be made with openssl
//! (docs/SECURITY.md).

use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use uavmeta_proto::config::{is_host_name, HOST_NAME_RULE};
use uavmeta_proto::fs::FileError;

#[derive(Debug, thiserror::Error)]
pub enum CertsError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    #[error("{}: already exists; remove it (and its key) to make a new one", path.display())]
    Exists { path: PathBuf },
    #[error("host name `{0}`: expected {HOST_NAME_RULE}, and not `ca`")]
    BadName(String),
}

/// What [`make`] wrote.
#[derive(Debug, Clone)]
pub struct Made {
    pub ca: PathBuf,
    /// Whether the CA was made now (else an existing one signed).
    pub new_ca: bool,
    pub certificate: PathBuf,
    pub private_key: PathBuf,
}

/// Makes (or reuses) `dir`'s CA and signs a certificate for `host`, valid for `host` and
/// `addresses` (IP addresses or DNS names).
pub fn make(dir: &Path, host: &str, addresses: &[String]) -> Result<Made, CertsError> {
    if !is_host_name(host) || host == "ca" {
        return Err(CertsError::BadName(host.into()));
    }
    std::fs::create_dir_all(dir).map_err(FileError::at(dir, "create"))?;
    let (certificate, private_key) = (
        dir.join(format!("{host}.pem")),
        dir.join(format!("{host}.key")),
    );
    for path in [&certificate, &private_key] {
        if path.exists() {
            return Err(CertsError::Exists { path: path.clone() });
        }
    }
    let (ca_pem, ca_key) = (dir.join("ca.pem"), dir.join("ca.key"));
    let new_ca = !ca_pem.exists();
    if new_ca {
        make_ca(&ca_pem, &ca_key)?;
    }
    let issuer = load_ca(&ca_pem, &ca_key)?;
    let mut names = vec![host.to_string()];
    names.extend(addresses.iter().cloned());
    let mut params = CertificateParams::new(names).map_err(invalid(&certificate))?;
    params.distinguished_name.push(DnType::CommonName, host);
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    let key = KeyPair::generate().map_err(invalid(&private_key))?;
    let cert = params
        .signed_by(&key, &issuer)
        .map_err(invalid(&certificate))?;
    write(&certificate, cert.pem().as_bytes(), 0o644)?;
    write(&private_key, key.serialize_pem().as_bytes(), 0o600)?;
    Ok(Made {
        ca: ca_pem,
        new_ca,
        certificate,
        private_key,
    })
}

fn make_ca(pem: &Path, key_path: &Path) -> Result<(), CertsError> {
    let mut params = CertificateParams::new(Vec::<String>::new()).map_err(invalid(pem))?;
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params
        .distinguished_name
        .push(DnType::CommonName, "uavmeta run CA");
    params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let key = KeyPair::generate().map_err(invalid(key_path))?;
    let cert = params.self_signed(&key).map_err(invalid(pem))?;
    write(key_path, key.serialize_pem().as_bytes(), 0o600)?;
    write(pem, cert.pem().as_bytes(), 0o644)
}

fn load_ca(pem: &Path, key_path: &Path) -> Result<Issuer<'static, KeyPair>, CertsError> {
    let read = |path: &Path| std::fs::read_to_string(path).map_err(FileError::at(path, "read"));
    let key = KeyPair::from_pem(&read(key_path)?).map_err(invalid(key_path))?;
    Issuer::from_ca_cert_pem(&read(pem)?, key).map_err(invalid(pem))
}

/// Writes a new file with `mode`, never over an existing one.
fn write(path: &Path, bytes: &[u8], mode: u32) -> Result<(), CertsError> {
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(mode)
        .open(path)
        .map_err(FileError::at(path, "create"))?;
    file.write_all(bytes)
        .map_err(FileError::at(path, "write"))?;
    Ok(())
}

fn invalid(path: &Path) -> impl FnOnce(rcgen::Error) -> CertsError {
    let path = path.to_path_buf();
    move |e| CertsError::Invalid {
        path,
        message: e.to_string(),
    }
}
