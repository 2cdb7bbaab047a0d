//! `[world]`: docs/MODEL.md section 1's grid, devices, UAV, channel and rain model. Read by
//! `uavmeta_world` (the environment, its heuristics and planner), and for the sizes of observations
//! and actions by every crate that holds a network or a dataset.

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use crate::layout::Layout;

use super::rules::{at_least, at_most, finite, is_weight, satisfies, toml_seed, within, Broken};

/// The largest number of devices a world may have: the zero-copy transition slot of
/// `proto::transport` stores observations in fixed-size arrays of `2 + MAX_DEVICES` entries.
pub const MAX_DEVICES: usize = 64;

/// docs/MODEL.md section 1's moves by name, in action-index order: action `a = move * K + device`.
/// Exports and `uavmeta dataset inspect` name actions with them; `actors::world::Move` is the
/// world's own enum in the same order.
pub const MOVES: [&str; 5] = ["north", "south", "east", "west", "hover"];

/// The largest team: a team step keeps its UAVs' orders on the stack, `MAX_UAVS` of them.
pub const MAX_UAVS: usize = 8;

/// The most joint start cells a team's exact evaluation runs: past it, a fixed sample of this
/// many (docs/MODEL.md section 11; `uavmeta_world::rollout::start_worlds`).
pub const MAX_JOINT_STARTS: usize = 10_000;

/// How many joint start cells `uavs` UAVs have on a grid of `cells` cells, where exact
/// evaluation runs every one of them (a single UAV's always); `None` past [`MAX_JOINT_STARTS`],
/// where it runs a fixed sample of that many.
pub fn enumerated_starts(cells: usize, uavs: usize) -> Option<usize> {
    let count = cells.checked_pow(uavs as u32);
    count.filter(|&n| uavs == 1 || n <= MAX_JOINT_STARTS)
}

/// The largest grid side: the world precomputes a power table of grid_cells^2 x K entries.
pub const MAX_GRID_CELLS: u32 = 1024;

/// docs/MODEL.md section 1: the grid, the devices, the UAV, the channel and the rain model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct WorldConfig {
    /// Cells per side, L.
    #[default(10)]
    #[garde(custom(within(
        1..=MAX_GRID_CELLS,
        format!("between 1 and {MAX_GRID_CELLS} cells per side")
    )))]
    pub grid_cells: u32,
    /// Side of a cell in metres, r.
    #[default(100.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub cell_m: f64,
    /// Number of IoT devices, K.
    #[default(10)]
    #[garde(custom(at_least(1)), custom(at_most(MAX_DEVICES)))]
    pub devices: usize,
    /// Explicit device cells `[[x, y], ...]`; when absent, `layout_seed` draws distinct cells.
    pub device_cells: Option<Vec<[u32; 2]>>,
    /// Seed of the device layout when `device_cells` is absent.
    #[default(0)]
    #[garde(custom(toml_seed()))]
    pub layout_seed: u64,
    /// Importance weight delta_k: one number for every device, or one per device.
    #[default(Delta::Uniform(1.0))]
    #[garde(custom(satisfies(Delta::is_weights, "finite weights >= 0")))]
    pub delta: Delta,
    /// UAV height h in metres.
    #[default(100.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub height_m: f64,
    /// Episode length T in steps; the end of an episode is a time limit, not a terminal state.
    #[default(100)]
    #[garde(custom(within(1.., "at least 1 step")))]
    pub horizon: u32,
    /// AoI cap A_max.
    #[default(100)]
    #[garde(custom(within(1..=u32::from(u16::MAX), "between 1 and 65535")))]
    pub aoi_max: u32,
    /// Fixed start cell of the UAV (of every UAV of a team); uniform at random each episode when
    /// absent.
    pub start_cell: Option<[u32; 2]>,
    /// UAVs U over the same devices and grid (docs/MODEL.md section 11); 1 is the paper's world.
    #[default(1)]
    #[garde(custom(at_least(1)), custom(at_most(MAX_UAVS)))]
    #[serde(skip_serializing_if = "is_one")]
    pub uavs: usize,
    /// Each UAV may also serve no device (target K, no power and no AoI reset), as the authors'
    /// multi-UAV world allows; false keeps the paper's 5K actions.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub idle_action: bool,
    /// Cells a move covers; a move that would leave the grid stops at its edge (docs/MODEL.md
    /// section 1, P1b). The authors' multi-UAV world moves two.
    #[default(1)]
    #[garde(custom(at_least(1)))]
    #[serde(skip_serializing_if = "is_one_u32")]
    pub step_cells: u32,
    /// Channel gain at 1 m, g0, in dB.
    #[default(-30.0)]
    #[garde(custom(finite(.., "a finite number of dB")))]
    pub g0_db: f64,
    /// Bandwidth B in Hz.
    #[default(1e6)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub bandwidth_hz: f64,
    /// Bits per update M.
    #[default(5e6)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub bits: f64,
    /// Noise power sigma^2 in dBm.
    #[default(-100.0)]
    #[garde(custom(finite(.., "a finite number of dB")))]
    pub noise_dbm: f64,
    /// Which powers enter the reward: the scheduled device's only, or all K devices'.
    #[default(PowerTerm::Scheduled)]
    pub power_term: PowerTerm,
    /// Rain rate R in mm/h.
    #[default(12.5)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub rain_mm_per_h: f64,
    /// ITU-R P.838 coefficient phi (k).
    #[default(0.2051)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub rain_phi: f64,
    /// ITU-R P.838 exponent varphi (alpha).
    #[default(0.9679)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub rain_varphi: f64,
}

impl WorldConfig {
    /// The observation and action layout of this world.
    pub fn layout(&self) -> Layout {
        Layout::team(self.devices, self.uavs, self.idle_action)
    }

    /// The episodes of an exact evaluation: one per start cell of the UAV, per joint start cell
    /// of a team up to [`MAX_JOINT_STARTS`], or one where the start is fixed.
    pub fn exact_starts(&self) -> usize {
        if self.start_cell.is_some() {
            return 1;
        }
        let cells = self.grid_cells as usize * self.grid_cells as usize;
        enumerated_starts(cells, self.uavs).unwrap_or(MAX_JOINT_STARTS)
    }

    /// Divisors that normalise one UAV's raw observation for the networks: x/(L-1), y/(L-1),
    /// A/aoi_max.
    pub fn observation_scale(&self) -> Vec<f32> {
        let span = (self.grid_cells.max(2) - 1) as f32;
        let mut scale = vec![span, span];
        scale.resize(self.layout().observation_len(), self.aoi_max as f32);
        scale
    }

    /// delta_k for every device.
    pub fn delta_per_device(&self) -> Vec<f64> {
        match &self.delta {
            Delta::Uniform(d) => vec![*d; self.devices],
            Delta::PerDevice(d) => d.clone(),
        }
    }

    /// Rain-specific attenuation gamma_R = phi * R^varphi in dB/km.
    pub fn rain_attenuation_db_per_km(&self) -> f64 {
        self.rain_phi * self.rain_mm_per_h.powf(self.rain_varphi)
    }

    /// The largest transmit power any step can ask for, in mW: docs/MODEL.md section 1's
    /// P = (2^(M/B) - 1) sigma^2 / g0 (h^2 + d^2) at the grid's longest distance, with rain's
    /// attenuation, for every device where the power term sums them (as `uavmeta_world` builds
    /// its tables).
    pub fn largest_power_mw(&self) -> f64 {
        let noise_w = 10f64.powf((self.noise_dbm - 30.0) / 10.0);
        let g0 = 10f64.powf(self.g0_db / 10.0);
        let watts_per_m2 = (2f64.powf(self.bits / self.bandwidth_hz) - 1.0) * noise_w / g0;
        let side = f64::from(self.grid_cells) * self.cell_m;
        let slant2 = self.height_m * self.height_m + 2.0 * side * side;
        let rain = 10f64.powf(self.rain_attenuation_db_per_km() * slant2.sqrt() / 1e3 / 10.0);
        let devices = match self.power_term {
            PowerTerm::AllDevices => self.devices as f64,
            _ => 1.0,
        };
        watts_per_m2 * slant2 * 1e3 * rain * devices
    }

    /// Whether cell `c` is inside the grid.
    fn inside(&self, c: [u32; 2]) -> bool {
        c[0] < self.grid_cells && c[1] < self.grid_cells
    }

    /// The devices fit the grid, one to a cell and each with its weight; the start is inside.
    pub(super) fn check_layout(&self) -> Result<(), Broken> {
        let cells = self.grid_cells as usize * self.grid_cells as usize;
        if self.devices > cells {
            let expected = format!("between 1 and the number of cells, grid_cells^2 = {cells}");
            return Err(Broken::new("world.devices", &self.devices, expected));
        }
        if let Some(device_cells) = &self.device_cells {
            self.check_device_cells("world.device_cells", device_cells)?;
        }
        if let Delta::PerDevice(d) = &self.delta {
            if d.len() != self.devices {
                let expected = format!("one weight or {} weights", self.devices);
                return Err(Broken::new("world.delta", d, expected));
            }
        }
        match self.start_cell {
            Some(c) if !self.inside(c) => Err(Broken::new(
                "world.start_cell",
                &c,
                "a cell inside the grid",
            )),
            _ => Ok(()),
        }
    }

    /// One distinct cell inside the grid per device, `cells` being the value of `key`.
    pub(super) fn check_device_cells(&self, key: &str, cells: &[[u32; 2]]) -> Result<(), Broken> {
        if cells.len() != self.devices {
            let expected = format!(
                "one cell per device: {} cells (world.devices)",
                self.devices
            );
            return Err(Broken::new(key, &cells, expected));
        }
        for (i, c) in cells.iter().enumerate() {
            let key = format!("{key}[{i}]");
            if !self.inside(*c) {
                let expected = format!(
                    "a cell inside the grid, each index below grid_cells = {}",
                    self.grid_cells
                );
                return Err(Broken::new(key, c, expected));
            }
            if cells[..i].contains(c) {
                return Err(Broken::new(key, c, "a cell no other device occupies"));
            }
        }
        Ok(())
    }
}

/// delta: a number for every device, or a list with one per device.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Delta {
    Uniform(f64),
    PerDevice(Vec<f64>),
}

impl Delta {
    /// The weights as written: one, or one per device.
    pub fn weights(&self) -> &[f64] {
        match self {
            Delta::Uniform(d) => std::slice::from_ref(d),
            Delta::PerDevice(d) => d,
        }
    }

    /// Whether every weight is finite and at least 0.
    fn is_weights(&self) -> bool {
        self.weights().iter().all(is_weight)
    }
}

/// Which transmit powers the reward charges.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PowerTerm {
    /// Only the scheduled device transmits, so the sum over devices is its one power.
    Scheduled,
    /// The literal reading: the sum over all K devices of the power each would need.
    AllDevices,
}

// Keys a team adds are written out only where they leave the paper's world, so a one-UAV
// config serialises, and hashes, as it did before teams.
fn is_one(n: &usize) -> bool {
    *n == 1
}

fn is_one_u32(n: &u32) -> bool {
    *n == 1
}
