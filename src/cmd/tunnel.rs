//! `uavmeta tunnel serve|join`: remote actor hosts (see `uavmeta_tunnel`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use uavmeta_tunnel::{JoinOptions, Security};

use super::launch::RunArgs;

#[derive(Subcommand, Debug)]
pub enum TunnelCommand {
    /// On the learner's host: serve the run to remote actor hosts on `tunnel.listen` (the
    /// launcher starts this when the key is set).
    Serve(RunArgs),
    /// On an actor host: join a run served at ENDPOINT, then start actors with
    /// `uavmeta actor --run DIR --task T --seed S`.
    Join(JoinArgs),
    /// Make the run's CA in DIR (once) and a certificate and key for one host, for a tls/
    /// endpoint: copy ca.pem and the host's NAME.pem and NAME.key to that host.
    Certs(CertsArgs),
}

#[derive(Args, Debug)]
pub struct CertsArgs {
    /// Where the CA and the certificates live (ca.key stays here, with the learner's host).
    #[arg(long, value_name = "DIR")]
    pub dir: PathBuf,
    /// The host's name: its files are NAME.pem and NAME.key.
    #[arg(long, value_name = "NAME")]
    pub host: String,
    /// An address or DNS name the certificate is valid for (repeat): the learner host's must
    /// include the one remote hosts connect to.
    #[arg(long = "address", value_name = "ADDRESS")]
    pub addresses: Vec<String>,
}

#[derive(Args, Debug)]
pub struct JoinArgs {
    /// The learner host's Zenoh endpoint (its `tunnel.listen`, with its address), such as
    /// tcp/10.0.0.1:7447.
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: String,
    /// The run's id, as the learner host's `uavmeta tunnel serve` logs it.
    #[arg(long = "run-id", value_name = "ID")]
    pub run_id: String,
    /// This host's directory for the run, where its actors run.
    #[arg(long, value_name = "DIR")]
    pub dir: PathBuf,
    /// This host's iceoryx2 domain (`run.domain`); default iceoryx2's.
    #[arg(long, default_value = "")]
    pub domain: String,
    /// This host's name in the learner's Prometheus targets (label `host`); default the host name.
    #[arg(long)]
    pub host: Option<String>,
    /// The address this host's /metrics listen on and are scraped at.
    #[arg(long, default_value = "127.0.0.1", value_name = "ADDRESS")]
    pub metrics_host: String,
    /// Give up after this many seconds without reaching the learner's host.
    #[arg(long, default_value_t = 120.0, value_name = "SECONDS")]
    pub patience: f64,
    /// The run's CA certificate (PEM), which signed the learner host's certificate.
    #[arg(long, value_name = "FILE")]
    pub ca: Option<PathBuf>,
    /// This host's certificate (PEM), signed by the run's CA (`uavmeta tunnel certs`).
    #[arg(long, value_name = "FILE")]
    pub certificate: Option<PathBuf>,
    /// This host's private key (PEM).
    #[arg(long = "private-key", value_name = "FILE")]
    pub private_key: Option<PathBuf>,
    /// A file whose line `user:password` the learner host's tunnel.credentials lists; a file,
    /// so that the password is never on a command line.
    #[arg(long, value_name = "FILE")]
    pub credentials: Option<PathBuf>,
}

pub fn run(command: TunnelCommand) -> Result<()> {
    match command {
        TunnelCommand::Serve(args) => {
            let (run, config) = args.open()?;
            if config.tunnel.listen.is_empty() {
                bail!(
                    "{}: tunnel.listen is empty; set it to the Zenoh endpoint to serve on, such as \
                     tcp/0.0.0.0:7447",
                    config.origin
                );
            }
            uavmeta_tunnel::serve(&run, &config)?;
        }
        TunnelCommand::Certs(args) => {
            let made = uavmeta_tunnel::certs::make(&args.dir, &args.host, &args.addresses)?;
            let ca = match made.new_ca {
                true => "made",
                false => "reused",
            };
            println!(
                "CA {} ({ca}); host `{}`: {} and {}",
                made.ca.display(),
                args.host,
                made.certificate.display(),
                made.private_key.display()
            );
        }
        TunnelCommand::Join(args) => {
            if !(args.patience.is_finite() && args.patience >= 0.0) {
                bail!("--patience {}: expected seconds >= 0", args.patience);
            }
            let host = match args.host {
                Some(host) => host,
                None => std::fs::read_to_string("/proc/sys/kernel/hostname")?
                    .trim()
                    .to_string(),
            };
            uavmeta_tunnel::join(&JoinOptions {
                endpoint: args.connect,
                run_id: args.run_id,
                dir: args.dir,
                domain: args.domain,
                host,
                metrics_host: args.metrics_host,
                patience: Duration::from_secs_f64(args.patience),
                security: Security {
                    ca: args.ca,
                    certificate: args.certificate,
                    private_key: args.private_key,
                    credentials: args.credentials,
                },
            })?;
        }
    }
    Ok(())
}
