//! `[[tasks]]`: docs/MODEL.md sections 2-3's tasks, each the world with its lambda and optional
//! rain. Read by `uavmeta_world` (a world is built for one task) and by every stage that names
//! tasks.

use std::str::FromStr;

use garde::Validate;
use serde::{Deserialize, Serialize};

use super::rules::{finite, toml_seed, within, Broken};
use super::WorldConfig;

/// A rectangle of cells, both corners inclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RainZone {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl RainZone {
    #[inline]
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..=self.x1).contains(&x) && (self.y0..=self.y1).contains(&y)
    }
}

impl FromStr for RainZone {
    type Err = String;

    /// Parses `x0,y0,x1,y1`, the form of the `--rain` flag.
    fn from_str(s: &str) -> Result<Self, String> {
        let parts: Vec<u32> = s
            .split(',')
            .map(|p| p.trim().parse::<u32>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("`{s}`: expected four cell indices x0,y0,x1,y1"))?;
        match parts[..] {
            [x0, y0, x1, y1] => Ok(Self { x0, y0, x1, y1 }),
            _ => Err(format!("`{s}`: expected four cell indices x0,y0,x1,y1")),
        }
    }
}

/// The authors' risky region (docs/MODEL.md section 11): a rectangle of cells, both corners
/// inclusive, where each transmission costs `penalty` (in reward units) with probability
/// `probability`, drawn from the world's seed; exact evaluation charges its expectation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields)]
#[garde(allow_unvalidated)]
pub struct RiskyRegion {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
    #[garde(custom(finite(0.0.., "a finite penalty >= 0")))]
    pub penalty: f64,
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub probability: f64,
}

impl RiskyRegion {
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..=self.x1).contains(&x) && (self.y0..=self.y1).contains(&y)
    }

    /// What a transmission from inside it costs on average: penalty times probability.
    pub fn expected_penalty(&self) -> f64 {
        self.penalty * self.probability
    }
}

/// Whether a task is used for meta-training or held out for meta-testing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TaskRole {
    MetaTrain,
    MetaTest,
}

/// docs/MODEL.md sections 2-3: one task is the world with its lambda and optional rain.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields)]
#[garde(allow_unvalidated)]
pub struct TaskConfig {
    pub name: String,
    /// The AoI-power trade-off.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub lambda: f64,
    pub role: TaskRole,
    #[serde(default)]
    pub rain: Option<RainZone>,
    /// Relocate the rain zone uniformly at random every this many steps.
    #[serde(default)]
    #[garde(inner(custom(within(1.., "at least 1 step"))))]
    pub rain_moves_every: Option<u32>,
    /// The authors' risky region, if the task has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[garde(dive)]
    pub risky: Option<RiskyRegion>,
    /// The task's own device cells, in place of the world's layout (docs/MODEL.md section 11):
    /// tasks that also vary where the devices are, as the authors' follow-up meta-trains over.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_cells: Option<Vec<[u32; 2]>>,
    /// The seed of the task's own device layout, when it has no `device_cells`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[garde(inner(custom(toml_seed())))]
    pub layout_seed: Option<u64>,
}

impl TaskConfig {
    /// As [`TaskConfig::one_off`], its rain zone moving every `every` steps
    /// (`--rain-moves-every N`); the name says so.
    pub fn one_off_moving(lambda: f64, rain: RainZone, every: u32) -> Self {
        let task = Self::one_off(lambda, Some(rain));
        Self {
            name: format!("{}-moves-{every}", task.name),
            rain_moves_every: Some(every),
            ..task
        }
    }

    /// A task given on the command line (`--lambda X [--rain x0,y0,x1,y1]`) instead of by name.
    pub fn one_off(lambda: f64, rain: Option<RainZone>) -> Self {
        let name = match rain {
            None => format!("lambda-{lambda}"),
            Some(r) => format!("lambda-{lambda}-rain-{}-{}-{}-{}", r.x0, r.y0, r.x1, r.y1),
        };
        Self {
            name,
            lambda,
            role: TaskRole::MetaTest,
            rain,
            rain_moves_every: None,
            risky: None,
            device_cells: None,
            layout_seed: None,
        }
    }
}

/// The paper's setting (docs/MODEL.md section 2): meta-train on eight lambdas, meta-test on lambda
/// = 300.
pub(super) fn default_tasks() -> Vec<TaskConfig> {
    let mut tasks: Vec<TaskConfig> = [0.0, 100.0, 200.0, 400.0, 500.0, 600.0, 800.0, 1000.0]
        .into_iter()
        .map(|lambda| TaskConfig {
            name: format!("lambda-{lambda}"),
            lambda,
            role: TaskRole::MetaTrain,
            rain: None,
            rain_moves_every: None,
            risky: None,
            device_cells: None,
            layout_seed: None,
        })
        .collect();
    tasks.push(TaskConfig::one_off(300.0, None));
    tasks
}

impl TaskConfig {
    /// A task's own layout is one of `device_cells` and `layout_seed`, its cells the world's
    /// rules for `world.device_cells`.
    pub(super) fn check_layout(&self, index: usize, world: &WorldConfig) -> Result<(), Broken> {
        match (&self.device_cells, self.layout_seed) {
            (Some(_), Some(seed)) => Err(Broken::new(
                format!("tasks[{index}].layout_seed"),
                &seed,
                "no layout_seed beside the task's device_cells (one layout a task)",
            )),
            (Some(cells), None) => {
                world.check_device_cells(&format!("tasks[{index}].device_cells"), cells)
            }
            _ => Ok(()),
        }
    }

    /// The rain zone and the risky region, task `index`'s, are inside a grid of `grid_cells` a
    /// side, and only a task with rain moves it.
    pub(super) fn check_rain(&self, index: usize, grid_cells: u32) -> Result<(), Broken> {
        let n = grid_cells;
        let outside = |r: &RainZone| r.x0 > r.x1 || r.y0 > r.y1 || r.x1 >= n || r.y1 >= n;
        if let Some(r) = self.rain.filter(outside) {
            let expected = format!("a rectangle inside the grid: x0 <= x1 < {n}, y0 <= y1 < {n}");
            return Err(Broken::new(format!("tasks[{index}].rain"), &r, expected));
        }
        let off_grid = |r: &RiskyRegion| r.x0 > r.x1 || r.y0 > r.y1 || r.x1 >= n || r.y1 >= n;
        if let Some(r) = self.risky.filter(off_grid) {
            let expected = format!("a rectangle inside the grid: x0 <= x1 < {n}, y0 <= y1 < {n}");
            let corners = [r.x0, r.y0, r.x1, r.y1];
            return Err(Broken::new(
                format!("tasks[{index}].risky"),
                &corners,
                expected,
            ));
        }
        match (self.rain_moves_every, self.rain) {
            (Some(_), None) => Err(Broken::new(
                format!("tasks[{index}].rain_moves_every"),
                &self.rain_moves_every,
                "a `rain` zone to move",
            )),
            _ => Ok(()),
        }
    }
}
