//! The handshake before any bridging: a remote host asks the learner's host for a run by Zenoh
//! query, and each side checks the other's schema version.

use std::collections::BTreeMap;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use uavmeta_proto::config::{Config, TunnelConfig};
use uavmeta_proto::payload::SCHEMA_VERSION;
use uavmeta_runtime::run_dir::RunDir;
use zenoh::query::Query;
use zenoh::{Session, Wait};

use crate::session::run_key;
use crate::TunnelError;

/// How long a remote host waits for the answer to one handshake query.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(3);

/// What a remote host says when it asks for a run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Hello {
    pub schema_version: u32,
    /// The host's name, in logs and in the Prometheus `host` label.
    pub host: String,
}

/// The learner host's answer: what a remote host needs to make a directory for the run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunInfo {
    pub schema_version: u32,
    pub run_id: String,
    /// [`RunDir::hash`], which every batch carries.
    pub run_hash: u64,
    /// The run's config.toml.
    pub config: String,
    /// The tasks the asking host may serve (`tunnel.hosts`).
    pub tasks: Vec<String>,
}

impl RunInfo {
    pub fn new(run: &RunDir, config: &Config) -> Self {
        let shared = Config {
            tunnel: TunnelConfig::default(),
            ..config.clone()
        };
        Self {
            schema_version: SCHEMA_VERSION,
            run_id: run.id().into(),
            run_hash: run.hash(),
            config: shared.to_toml_string(),
            tasks: Vec::new(),
        }
    }
}

/// The tasks each remote host of `config.tunnel.hosts` may serve, by name.
pub fn served(config: &Config) -> BTreeMap<String, Vec<String>> {
    (config.tunnel.hosts.keys())
        .map(|host| {
            let tasks = config.tunnel.tasks_of(host, &config.tasks);
            (host.clone(), tasks.iter().map(|t| t.name.clone()).collect())
        })
        .collect()
}

/// The learner host's side: the answer to `hello`, with the tasks the host may serve (`served`),
/// or the refusal to send back (and log).
pub fn answer(
    info: &RunInfo,
    served: &BTreeMap<String, Vec<String>>,
    hello: &Hello,
) -> Result<RunInfo, String> {
    if hello.schema_version != info.schema_version {
        return Err(format!(
            "host `{}` speaks schema version {}, but run `{}` speaks version {}; run the same \
             uavmeta build on every host",
            hello.host, hello.schema_version, info.run_id, info.schema_version
        ));
    }
    let tasks = served.get(&hello.host).ok_or_else(|| {
        format!(
            "host `{}` is not in tunnel.hosts of run `{}`: it may serve no task",
            hello.host, info.run_id
        )
    })?;
    Ok(RunInfo {
        tasks: tasks.clone(),
        ..info.clone()
    })
}

/// Answers one query on the run's key, logging every refusal. A query of any other key that
/// the run's matches (a wildcard such as `uavmeta/runs/*`) gets no answer, as a run id that is
/// not served: the run id is told only to a host that names it.
pub(crate) fn reply(query: &Query, info: &RunInfo, served: &BTreeMap<String, Vec<String>>) {
    if query.key_expr().as_str() != run_key(&info.run_id) {
        tracing::debug!(key = %query.key_expr(), "ignored a handshake that does not name the run");
        return;
    }
    let hello = query
        .payload()
        .ok_or_else(|| "a handshake without a Hello".to_string())
        .and_then(|bytes| {
            serde_json::from_slice::<Hello>(&bytes.to_bytes()).map_err(|e| e.to_string())
        });
    let answer = hello.and_then(|hello| {
        let answer = answer(info, served, &hello);
        match &answer {
            Ok(_) => tracing::info!(host = %hello.host, "a remote actor host joined the run"),
            Err(refusal) => tracing::error!("refused a remote actor host: {refusal}"),
        }
        answer
    });
    let sent = match answer {
        Ok(info) => query
            .reply(
                query.key_expr().clone(),
                serde_json::to_vec(&info).expect("serialises"),
            )
            .wait(),
        Err(refusal) => query.reply_err(refusal).wait(),
    };
    if let Err(error) = sent {
        tracing::warn!(%error, "cannot answer a remote host's handshake");
    }
}

/// What one handshake attempt came to.
pub(crate) enum Outcome {
    Joined(RunInfo),
    /// No answer: the learner's tunnel is not (yet) up.
    Unanswered,
}

/// The remote host's side: asks `endpoint`'s session for `run_id`; refusals and schema
/// mismatches are errors, silence is [`Outcome::Unanswered`] (a run id not served is silence
/// too: nothing tells a stranger which runs are).
pub(crate) fn ask(
    session: &Session,
    endpoint: &str,
    run_id: &str,
    hello: &Hello,
) -> Result<Outcome, TunnelError> {
    let replies = session
        .get(run_key(run_id))
        .payload(serde_json::to_vec(hello).expect("serialises"))
        .timeout(ANSWER_TIMEOUT)
        .wait()
        .map_err(TunnelError::zenoh(endpoint))?;
    if let Ok(reply) = replies.recv() {
        let answer = match reply.result() {
            Ok(sample) => serde_json::from_slice::<RunInfo>(&sample.payload().to_bytes())
                .map_err(|e| format!("an unreadable answer: {e}")),
            Err(refusal) => Err(refusal.payload().try_to_string().map_or_else(
                |_| "a refusal without a reason".to_string(),
                |s| s.into_owned(),
            )),
        };
        let info = answer.map_err(|message| TunnelError::Refused {
            endpoint: endpoint.into(),
            message,
        })?;
        if info.schema_version != SCHEMA_VERSION {
            return Err(TunnelError::SchemaMismatch {
                endpoint: endpoint.into(),
                theirs: info.schema_version,
                ours: SCHEMA_VERSION,
            });
        }
        return Ok(Outcome::Joined(info));
    }
    Ok(Outcome::Unanswered)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session;

    fn info() -> RunInfo {
        RunInfo {
            schema_version: SCHEMA_VERSION,
            run_id: "r-0000".into(),
            run_hash: 7,
            config: String::new(),
            tasks: Vec::new(),
        }
    }

    /// Host `b` may serve task `t`.
    fn served_b() -> BTreeMap<String, Vec<String>> {
        BTreeMap::from([("b".to_string(), vec!["t".to_string()])])
    }

    #[test]
    fn a_host_of_another_schema_version_is_refused_with_both_versions_named() {
        let hello = Hello {
            schema_version: SCHEMA_VERSION + 1,
            host: "b".into(),
        };
        let refusal = answer(&info(), &served_b(), &hello).expect_err("refused");
        assert!(refusal.contains(&format!("schema version {}", SCHEMA_VERSION + 1)));
        assert!(refusal.contains(&format!("speaks version {SCHEMA_VERSION}")));
        assert!(refusal.contains("`b`"));
        let hello = Hello {
            schema_version: SCHEMA_VERSION,
            host: "b".into(),
        };
        let joined = answer(&info(), &served_b(), &hello).expect("joined");
        assert_eq!((joined.run_hash, joined.tasks), (7, vec!["t".to_string()]));
        let stranger = Hello {
            host: "c".into(),
            ..hello
        };
        let refusal = answer(&info(), &served_b(), &stranger).expect_err("refused");
        assert!(refusal.contains("`c` is not in tunnel.hosts"), "{refusal}");
    }

    /// `ask` until it gets an answer: a fresh client learns the server's declarations shortly
    /// after it connects.
    fn ask_until_answered(
        client: &Session,
        endpoint: &str,
        run: &str,
    ) -> Result<RunInfo, TunnelError> {
        let hello = Hello {
            schema_version: SCHEMA_VERSION,
            host: "b".into(),
        };
        ask_with(client, endpoint, run, &hello)
    }

    fn ask_with(
        client: &Session,
        endpoint: &str,
        run: &str,
        hello: &Hello,
    ) -> Result<RunInfo, TunnelError> {
        let start = std::time::Instant::now();
        loop {
            if let Outcome::Joined(info) = ask(client, endpoint, run, hello)? {
                return Ok(info);
            }
            assert!(start.elapsed() < Duration::from_secs(60), "never answered");
        }
    }

    #[test]
    fn each_side_refuses_the_others_schema_version_over_zenoh() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let server = session::listen(&endpoint, &Default::default(), None).expect("listen");
        let ours = info();
        let _current = server
            .declare_queryable(run_key("r-0000"))
            .callback(move |query| reply(&query, &ours, &served_b()))
            .wait()
            .expect("queryable");
        // A learner host of an older build that does not check: only the remote side can refuse.
        let older = RunInfo {
            schema_version: SCHEMA_VERSION - 1,
            ..info()
        };
        let _older = server
            .declare_queryable(run_key("r-1111"))
            .callback(move |query| {
                let bytes = serde_json::to_vec(&older).expect("serialises");
                let _ = query.reply(query.key_expr().clone(), bytes).wait();
            })
            .wait()
            .expect("queryable");
        let client = session::connect(&endpoint, &Default::default()).expect("connect");
        assert_eq!(
            ask_until_answered(&client, &endpoint, "r-0000")
                .expect("joined")
                .run_hash,
            7
        );

        let newer = Hello {
            schema_version: SCHEMA_VERSION + 1,
            host: "b".into(),
        };
        match ask_with(&client, &endpoint, "r-0000", &newer) {
            Err(TunnelError::Refused { message, .. }) => {
                assert!(
                    message.contains(&format!("schema version {}", SCHEMA_VERSION + 1)),
                    "{message}"
                );
            }
            other => panic!("a newer remote host was not refused: {other:?}"),
        }
        match ask_until_answered(&client, &endpoint, "r-1111") {
            Err(error @ TunnelError::SchemaMismatch { .. }) => {
                let message = error.to_string();
                assert!(
                    message.contains(&format!("schema version {}", SCHEMA_VERSION - 1)),
                    "{message}"
                );
                assert!(message.contains(&endpoint), "{message}");
            }
            other => panic!("an older learner host was not refused: {other:?}"),
        }
    }
}
