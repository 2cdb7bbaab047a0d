//! What the agent tests share: configs/default.toml on the small world of the planner's tests.

use uavmeta_proto::config::Config;

pub const DEFAULT_CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/default.toml");

/// configs/default.toml on the planner tests' world (4 x 4 cells of 200 m, 3 devices, 20 steps,
/// layout seed 3), with `settings` (`--set` syntax) after it.
pub fn small_world(settings: &[&str]) -> Config {
    let sets: Vec<String> = [
        "world.grid_cells=4",
        "world.devices=3",
        "world.horizon=20",
        "world.cell_m=200",
        "world.layout_seed=3",
    ]
    .iter()
    .chain(settings)
    .map(|s| s.to_string())
    .collect();
    Config::load(DEFAULT_CONFIG.as_ref(), &sets).unwrap()
}
