//! What a training loop reports as it goes, for offline training and meta-training alike: a CSV
//! log of one row per epoch, a progress bar on the terminal, and [`OnStep`], the hook its caller
//! hears every step through.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use uavmeta_proto::fs::FileError;

/// A CSV file written line by line, each line flushed as it is written so an interrupted run
/// keeps its rows.
pub struct CsvLog {
    path: PathBuf,
    file: BufWriter<File>,
}

impl CsvLog {
    /// A new log at `path` (its directory created if need be) that starts with `header`.
    pub fn create(path: &Path, header: &str) -> Result<Self, FileError> {
        Self::resume(path, header, |_| false)
    }

    /// A new log at `path` that starts with `header`, then the rows of the log that was there for
    /// which `keep` holds: those a resumed run does not repeat.
    pub fn resume(
        path: &Path,
        header: &str,
        keep: impl Fn(&str) -> bool,
    ) -> Result<Self, FileError> {
        let old = std::fs::read_to_string(path).unwrap_or_default();
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(FileError::at(path, "create the directory of"))?;
        }
        let file = File::create(path).map_err(FileError::at(path, "create"))?;
        let mut log = Self {
            path: path.to_path_buf(),
            file: BufWriter::new(file),
        };
        log.line(header)?;
        for line in old.lines().skip(1).filter(|line| keep(line)) {
            log.line(line)?;
        }
        Ok(log)
    }

    /// Appends `line` and flushes it.
    pub fn line(&mut self, line: &str) -> Result<(), FileError> {
        writeln!(self.file, "{line}")
            .and_then(|()| self.file.flush())
            .map_err(FileError::at(&self.path, "write"))
    }
}

/// A progress bar of `len` units on the terminal, drawn with the indicatif `template`; hidden
/// (but still counting) when `enabled` is false.
pub fn progress_bar(enabled: bool, len: u64, template: &str) -> ProgressBar {
    if !enabled {
        return ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::hidden());
    }
    ProgressBar::new(len)
        .with_style(ProgressStyle::with_template(template).expect("the template is valid"))
}

/// What a long computation calls at every step (a gradient step of offline training, an outer
/// step of MAML), so that its caller hears it is making progress: a process of a run beats its
/// heartbeat there, so that its supervisor does not take an epoch over a large dataset for a hang.
/// The default calls nothing. It sees no figures and changes none.
#[derive(Clone, Default)]
pub struct OnStep(Option<Arc<dyn Fn() + Send + Sync>>);

impl OnStep {
    /// A hook that calls `f` at every step.
    pub fn new(f: impl Fn() + Send + Sync + 'static) -> Self {
        Self(Some(Arc::new(f)))
    }

    /// One step done.
    pub fn step(&self) {
        if let Some(f) = &self.0 {
            f();
        }
    }
}
