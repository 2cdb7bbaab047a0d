//! `[planner]`: the planner reference's beam search (docs/MODEL.md section 5). Read by
//! `uavmeta_world::planner`.

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{is_weight, list_of, within, Broken};
use super::{WorldConfig, MOVES};

/// The planner reference (docs/MODEL.md section 5, `uavmeta_world::planner`): a beam search over
/// the horizon that knows the world, the row every method's gap to "achievable" is read against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct PlannerConfig {
    /// The planner's effort: states kept per step of the beam search, and the schedule search's
    /// patience, one kick per 4 of them (world/src/schedule.rs). Exact (dynamic programming) once
    /// the beam holds every distinct state; on the default world 4x wider (1024) gains under
    /// 0.2% at 4x the time (docs/EXPERIMENTS.md, P and P3).
    #[default(256)]
    #[garde(custom(within(1.., "at least 1 state kept per step")))]
    pub beam_width: usize,
    /// The weights b of the power part of the search's cost-to-go estimate h
    /// (`uavmeta_world::planner`): the search runs once per weight and the cheapest plan is kept.
    /// The weight that ranks best moves with lambda (0.5 on lambda-300, 0.125 on lambda-1000 and
    /// lambda-2000), and the four together beat each alone on every lambda measured (each alone
    /// loses up to 4.2%, at lambda-2000), at four times the cost (docs/EXPERIMENTS.md, P2). 0
    /// ranks states by their cost so far and AoI alone.
    #[default(vec![0.5, 0.25, 0.125, 0.0625])]
    #[garde(custom(list_of(is_weight, "a non-empty list of finite weights >= 0")))]
    pub h_power_weights: Vec<f64>,
    /// The most memory one search may take, in MiB; a width and horizon that need more are
    /// refused up front.
    #[default(1024)]
    pub max_memory_mib: u64,
}

impl PlannerConfig {
    /// Bytes one search holds at its peak: width x T back-pointers, the beam, and one step's
    /// width x (5 x targets)^U children with their width x targets^U aged AoI vectors of K
    /// entries (one UAV of K targets: 5K children and K vectors).
    pub fn memory_bytes(&self, world: &WorldConfig) -> u128 {
        let (w, t, k, u) = (
            self.beam_width as u128,
            world.horizon as u128,
            world.devices as u128,
            world.uavs as u32,
        );
        let targets = world.layout().targets() as u128;
        let children = (MOVES.len() as u128 * targets).saturating_pow(u);
        let aged = targets.saturating_pow(u).saturating_mul(k * 2);
        let per_node = (t * 8 + 2 * k + 22 + 2 * u as u128)
            .saturating_add(children.saturating_mul(64))
            .saturating_add(aged);
        w.saturating_mul(per_node)
    }
}

impl PlannerConfig {
    /// The search on a one-UAV `world` fits `max_memory_mib`: every table has a planner row, so
    /// a config whose search would not fit is refused up front. A team's search grows as
    /// (5 x targets)^U and is refused where the planner is asked for ([`PlannerConfig::fits`]).
    pub(super) fn check_memory(&self, world: &WorldConfig) -> Result<(), Broken> {
        if world.uavs > 1 {
            return Ok(());
        }
        self.fits(world)
            .map_err(|expected| Broken::new("planner.beam_width", &self.beam_width, expected))
    }

    /// Whether one search on `world` fits `max_memory_mib`; if not, what was expected.
    pub fn fits(&self, world: &WorldConfig) -> Result<(), String> {
        let need = self.memory_bytes(world);
        if need <= (self.max_memory_mib as u128) << 20 {
            return Ok(());
        }
        Err(format!(
            "a search that fits planner.max_memory_mib = {} MiB; with world.horizon = {}, \
             world.devices = {} and world.uavs = {} it needs {} MiB",
            self.max_memory_mib,
            world.horizon,
            world.devices,
            world.uavs,
            need >> 20
        ))
    }
}
