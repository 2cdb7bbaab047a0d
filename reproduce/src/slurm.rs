//! `uavmeta reproduce --engine slurm`: the plan's graph (`OUT/plan.json`, `crate::plan`) handed
//! to a Slurm cluster.
//!
//! One `sbatch` job array per kind of job, whose index selects the job among that kind's in plan
//! order (`--stage KIND --index $SLURM_ARRAY_TASK_ID`), each array after the arrays of the kinds
//! it reads (`--dependency=afterok:`) and the figures job last. Only the jobs not done are
//! submitted, so submitting again after a failure runs what is left; a job that fails cancels
//! the arrays waiting on it (`--kill-on-invalid-dep=yes`), so nothing waits forever. OUT must be
//! on a filesystem every node sees. Slurm's commands are run as found on PATH, and whatever they
//! refuse is an error naming the command and its answer.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;
use uavmeta_proto::config::rules::{at_least, satisfies};

use crate::cache;
use crate::plan::{Kind, PlanFile};
use crate::ReproduceError;

/// `[reproduce.slurm]`: how `--engine slurm` submits (each key also a flag of `uavmeta
/// reproduce`, which wins over the file). Empty strings leave the choice to the cluster.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct SlurmConfig {
    /// `sbatch --partition`; empty: the cluster's default partition.
    #[garde(custom(satisfies(
        is_word,
        "a partition name (no spaces), or \"\" for the cluster's default"
    )))]
    pub partition: String,
    /// `sbatch --account`; empty: the user's default account.
    #[garde(custom(satisfies(
        is_word,
        "an account name (no spaces), or \"\" for the user's default"
    )))]
    pub account: String,
    /// `sbatch --time` of every job: minutes, MM:SS, HH:MM:SS, D-HH, D-HH:MM or D-HH:MM:SS;
    /// empty: the partition's default.
    #[garde(custom(satisfies(is_time, "a Slurm time limit (minutes, MM:SS, HH:MM:SS, D-HH, D-HH:MM or D-HH:MM:SS), or \"\" for the partition's default")))]
    pub time: String,
    /// `sbatch --cpus-per-task`: each job trains on one libtorch thread, so 1 unless a site
    /// wants whole cores per job.
    #[default(1)]
    #[garde(custom(at_least(1)))]
    pub cpus_per_task: usize,
    /// Further `sbatch` options, one argument each (`"--mem=4G"`, `"--qos=long"`).
    #[garde(custom(satisfies(|a: &Vec<String>| a.iter().all(|a| a.starts_with('-')), "a list of sbatch options, each starting with `-`")))]
    pub sbatch_args: Vec<String>,
}

fn is_word(value: &str) -> bool {
    !value.contains(char::is_whitespace)
}

/// Slurm's forms of a time limit, or empty.
fn is_time(value: &str) -> bool {
    let numbers = |s: &str, most: usize| {
        let parts: Vec<&str> = s.split(':').collect();
        parts.len() <= most
            && parts
                .iter()
                .all(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()))
    };
    match value.split_once('-') {
        _ if value.is_empty() => true,
        Some((days, rest)) => numbers(days, 1) && numbers(rest, 3),
        None => numbers(value, 3),
    }
}

/// What running a Slurm command can fail on.
#[derive(Debug, thiserror::Error)]
pub enum SlurmError {
    #[error("cannot run `{program}` (is Slurm's client installed and on PATH? Debian: apt-get install slurm-client): {source}")]
    Missing {
        program: String,
        source: std::io::Error,
    },
    #[error("`{command}` failed ({status}): {stderr}")]
    Refused {
        command: String,
        status: String,
        stderr: String,
    },
    #[error("`{command}` answered `{answer}`, not a job id")]
    Answer { command: String, answer: String },
    #[error("jobs {jobs} of an earlier submission of this plan are still queued or running: wait for them (`squeue -j {jobs}`) or cancel them (`scancel {}`), then submit again", jobs.replace(',', " "))]
    StillQueued { jobs: String },
}

/// Runs `program args`, its stdout on success.
fn run(program: &str, args: &[String]) -> Result<String, SlurmError> {
    let command = format!("{program} {}", args.join(" "));
    let output = Command::new(program)
        .args(args)
        .output()
        .map_err(|source| SlurmError::Missing {
            program: program.into(),
            source,
        })?;
    match output.status.success() {
        true => Ok(String::from_utf8_lossy(&output.stdout).into_owned()),
        false => Err(SlurmError::Refused {
            command,
            status: output.status.to_string(),
            stderr: String::from_utf8_lossy(&output.stderr).trim().to_string(),
        }),
    }
}

/// One submitted array: its kind, Slurm job id and the plan indices it runs.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Array {
    pub kind: Kind,
    pub job_id: String,
    pub indices: Vec<usize>,
}

/// `OUT/slurm/submitted.json`: the latest submission of the plan.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Submitted {
    pub arrays: Vec<Array>,
    /// Jobs of the plan already done, not submitted.
    pub skipped: usize,
}

impl Submitted {
    fn path(out: &Path) -> PathBuf {
        out.join("slurm").join("submitted.json")
    }

    pub(crate) fn read(out: &Path) -> Option<Self> {
        let text = std::fs::read_to_string(Self::path(out)).ok()?;
        serde_json::from_str(&text).ok()
    }

    fn ids(&self) -> String {
        let ids: Vec<&str> = self.arrays.iter().map(|a| a.job_id.as_str()).collect();
        ids.join(",")
    }

    /// What was submitted and the commands that follow it.
    pub fn describe(&self, out: &Path) -> String {
        let mut s = String::new();
        for a in &self.arrays {
            let _ = writeln!(
                s,
                "submitted {:<10} job {} ({} job{})",
                a.kind.name(),
                a.job_id,
                a.indices.len(),
                if a.indices.len() == 1 { "" } else { "s" }
            );
        }
        let _ = writeln!(s, "{} jobs of the plan were done already", self.skipped);
        if self.arrays.is_empty() {
            return s;
        }
        let ids = self.ids();
        let _ = writeln!(s, "follow them with:");
        let _ = writeln!(
            s,
            "  uavmeta reproduce --out {} --status --watch",
            out.display()
        );
        let _ = writeln!(s, "  squeue -j {ids}");
        let _ = writeln!(
            s,
            "  sacct -j {ids} --format=JobID,JobName,State,Elapsed,ExitCode"
        );
        let _ = writeln!(s, "  logs: {}", logs_dir(out).display());
        s
    }
}

fn logs_dir(out: &Path) -> PathBuf {
    out.join("slurm").join("logs")
}

/// Submits every job of `plan` not done in `out`, one array per kind; `job_command` runs one job
/// when `--stage KIND --index N` follow it.
pub fn submit(
    out: &Path,
    plan: &PlanFile,
    settings: &SlurmConfig,
    job_command: &[String],
) -> Result<Submitted, ReproduceError> {
    refuse_if_queued(out)?;
    uavmeta_meta::create_dir(&logs_dir(out))?;
    let mut submitted = Submitted {
        arrays: Vec::new(),
        skipped: 0,
    };
    for kind in Kind::ALL {
        let jobs: Vec<_> = plan.of(kind).collect();
        let indices: Vec<usize> = (0..jobs.len())
            .filter(|&i| kind == Kind::Figures || !PlanFile::done(out, jobs[i]))
            .collect();
        submitted.skipped += jobs.len() - indices.len();
        if indices.is_empty() {
            continue;
        }
        let after: Vec<&str> = (submitted.arrays.iter())
            .filter(|a| kind.after().contains(&a.kind))
            .map(|a| a.job_id.as_str())
            .collect();
        let script = write_script(out, kind, job_command)?;
        let args = sbatch_args(out, kind, &indices, &after, settings, &script);
        let job_id = parse_job_id("sbatch", &args, &run("sbatch", &args)?)?;
        tracing::info!(
            kind = kind.name(),
            job_id,
            jobs = indices.len(),
            "submitted"
        );
        submitted.arrays.push(Array {
            kind,
            job_id,
            indices,
        });
        // Recorded after every array, so a failure part-way leaves what was queued on record.
        let text = serde_json::to_string_pretty(&submitted).expect("always serialises");
        cache::write(&Submitted::path(out), &text)?;
    }
    Ok(submitted)
}

/// Refuses to submit while jobs of the latest submission are still in the queue.
fn refuse_if_queued(out: &Path) -> Result<(), ReproduceError> {
    let Some(last) = Submitted::read(out) else {
        return Ok(());
    };
    if last.arrays.is_empty() {
        return Ok(());
    }
    let args = vec![
        "-h".into(),
        "-o".into(),
        "%F".into(),
        "-j".into(),
        last.ids(),
    ];
    let mut queued: Vec<String> = match run("squeue", &args) {
        Ok(text) => text.split_whitespace().map(String::from).collect(),
        // squeue refuses ids the controller has forgotten: none of them is queued.
        Err(SlurmError::Refused { .. }) => Vec::new(),
        Err(e) => return Err(e.into()),
    };
    queued.sort();
    queued.dedup();
    match queued.is_empty() {
        true => Ok(()),
        false => Err(SlurmError::StillQueued {
            jobs: queued.join(","),
        }
        .into()),
    }
}

/// `OUT/slurm/KIND.sh`: runs the job of the array's index.
fn write_script(out: &Path, kind: Kind, job_command: &[String]) -> Result<PathBuf, ReproduceError> {
    let path = out.join("slurm").join(format!("{}.sh", kind.name()));
    let command: Vec<String> = job_command.iter().map(|a| quote(a)).collect();
    let text = format!(
        "#!/bin/sh\n# uavmeta reproduce: the plan's {kind} jobs (OUT/plan.json), one per array index.\n\
         exec {} --stage {kind} --index \"${{SLURM_ARRAY_TASK_ID:-0}}\"\n",
        command.join(" "),
        kind = kind.name(),
    );
    cache::write(&path, &text)?;
    Ok(path)
}

/// `arg` in single quotes for sh.
fn quote(arg: &str) -> String {
    format!("'{}'", arg.replace('\'', "'\\''"))
}

/// `sbatch`'s arguments for the array of `kind`'s `indices`, after the arrays `after`.
fn sbatch_args(
    out: &Path,
    kind: Kind,
    indices: &[usize],
    after: &[&str],
    s: &SlurmConfig,
    script: &Path,
) -> Vec<String> {
    let logs = logs_dir(out);
    let mut args = vec![
        "--parsable".to_string(),
        format!("--job-name=uavmeta-{}", kind.name()),
        format!("--output={}/{}-%A_%a.out", logs.display(), kind.name()),
        format!("--cpus-per-task={}", s.cpus_per_task),
        "--kill-on-invalid-dep=yes".into(),
    ];
    if kind != Kind::Figures {
        args.push(format!("--array={}", ranges(indices)));
    }
    if !after.is_empty() {
        args.push(format!("--dependency=afterok:{}", after.join(":")));
    }
    for (flag, value) in [
        ("partition", &s.partition),
        ("account", &s.account),
        ("time", &s.time),
    ] {
        if !value.is_empty() {
            args.push(format!("--{flag}={value}"));
        }
    }
    args.extend(s.sbatch_args.iter().cloned());
    args.push(script.display().to_string());
    args
}

/// `0-3,5,7-8`: sorted indices as Slurm's `--array` ranges.
fn ranges(indices: &[usize]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < indices.len() {
        let mut j = i;
        while j + 1 < indices.len() && indices[j + 1] == indices[j] + 1 {
            j += 1;
        }
        parts.push(match i == j {
            true => indices[i].to_string(),
            false => format!("{}-{}", indices[i], indices[j]),
        });
        i = j + 1;
    }
    parts.join(",")
}

/// The job id of `sbatch --parsable`'s answer (`ID` or `ID;CLUSTER`).
fn parse_job_id(program: &str, args: &[String], answer: &str) -> Result<String, SlurmError> {
    let id = answer.trim().split(';').next().unwrap_or("");
    match !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()) {
        true => Ok(id.to_string()),
        false => Err(SlurmError::Answer {
            command: format!("{program} {}", args.join(" ")),
            answer: answer.trim().to_string(),
        }),
    }
}

/// The number of the submission's jobs in the queue and the ids of those running, if squeue
/// answers.
pub(crate) fn squeue(submitted: &Submitted, plan: &PlanFile) -> Option<(usize, Vec<String>)> {
    let args = vec![
        "-h".into(),
        "-r".into(),
        "-o".into(),
        "%F %K %T".into(),
        "-j".into(),
        submitted.ids(),
    ];
    let text = run("squeue", &args).ok()?;
    let mut queued = 0;
    let mut running = Vec::new();
    for line in text.lines() {
        let cells: Vec<&str> = line.split_whitespace().collect();
        let [job, index, state] = cells[..] else {
            continue;
        };
        queued += 1;
        let array = submitted.arrays.iter().find(|a| a.job_id == job);
        let index = index.parse::<usize>().unwrap_or(0);
        let id = array.and_then(|a| plan.of(a.kind).nth(index));
        if let (Some(id), "RUNNING") = (id, state) {
            running.push(id.id.clone());
        }
    }
    Some((queued, running))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_become_slurm_ranges() {
        assert_eq!(ranges(&[0, 1, 2, 3, 5, 7, 8]), "0-3,5,7-8");
        assert_eq!(ranges(&[4]), "4");
    }

    #[test]
    fn time_limits_take_slurms_forms_only() {
        for ok in [
            "",
            "30",
            "30:00",
            "1:00:00",
            "2-12",
            "2-12:30",
            "2-12:30:00",
        ] {
            assert!(is_time(ok), "{ok}");
        }
        for bad in ["1h", "-1", "1:2:3:4", "2-", "a-1", " 30", "1::2"] {
            assert!(!is_time(bad), "{bad}");
        }
    }

    #[test]
    fn sbatch_answers_are_job_ids() {
        assert_eq!(parse_job_id("sbatch", &[], "42\n").unwrap(), "42");
        assert_eq!(parse_job_id("sbatch", &[], "42;cluster\n").unwrap(), "42");
        let error = parse_job_id("sbatch", &[], "Submitted batch job 42").unwrap_err();
        assert!(error.to_string().contains("not a job id"), "{error}");
    }

    #[test]
    fn a_missing_program_is_named() {
        let error = run("uavmeta-no-such-sbatch", &[]).unwrap_err().to_string();
        assert!(error.contains("`uavmeta-no-such-sbatch`"), "{error}");
    }

    #[test]
    fn scripts_quote_every_argument() {
        assert_eq!(quote("it's"), "'it'\\''s'");
    }
}
