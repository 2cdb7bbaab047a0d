//! The world as a run's own shots identify it (docs/MODEL.md section 5, "Dyna-CQL"): what the
//! fitted world is told is the world's form with no task in it (the grid and its moves, the AoI
//! update, the reward's form and the channel law); what it learns from the shots is each step's
//! power cost and whether the task has rain. It is what the model-based learner `dyna-cql` rolls
//! out in; nothing else trains or picks a policy in it.
//!
//! Each shot gives the power cost of one (cell, device) pair: the reward is -(sum_j delta_j A_j +
//! w P), with the AoI after the step in the next observation, so the cost w P is the reward less
//! the weighted AoI. The power weight w = lambda / K is the task's and is not told: the fitted
//! world charges the cost itself (its power weight is 1, so its "milliwatts" are w P). By section
//! 1's law that cost from cell (x, y) is c (h^2 + r^2 ((x - x_k)^2 + (y - y_k)^2)) with an unknown
//! c that absorbs w. Two fits, in turn:
//! - the law is linear in (x^2 + y^2, x, y, 1), so four cells not on one circle or line determine
//!   a device everywhere by least squares;
//! - else, since a device sits at a cell, each of the grid's cells is tried as the device's: the
//!   gain c is then the one unknown, and a cell whose law passes through every shot is a
//!   candidate. One candidate determines the device; several charge, at each cell, the largest
//!   cost any of them gives.
//!
//! A device neither fit explains is charged the largest cost the shots show from every cell it
//! was not seen at: a pessimistic model never favours a policy for going where the data has not
//! been. A shot whose transmission failed (its device's AoI not reset) says the task has rain,
//! which the fitted world does not model: then nothing is identified.

use nalgebra::{DMatrix, DVector};
use uavmeta_proto::config::{TaskConfig, TaskRole, WorldConfig};
use uavmeta_proto::dataset::Transition;

use crate::world::World;

/// Residual a fit may leave, as a share of the largest step cost in the shots: the rewards are
/// f32, so a law that holds fits to about 1e-7 of the cost.
const RESIDUAL_OF_COST: f64 = 1e-4;

/// A grid cell, (x, y).
type Cell = (u32, u32);

/// The power cost of each (cell, device) pair the shots schedule, in the order the shots first
/// schedule it (the order of the least-squares rows).
type Costs = Vec<((Cell, usize), f64)>;

/// The identified world and how many devices the shots determine.
#[derive(Debug, Clone)]
pub struct Identified {
    /// The world's form with the fitted power costs (power weight 1).
    pub world: World,
    /// Devices whose cost the shots determine everywhere (the others are pessimistic).
    pub devices_fitted: usize,
}

/// Why a run's shots identify no world.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Unidentified {
    #[error("there are no shots")]
    NoShots,
    #[error(
        "{0} shots are transmissions in outage: the task has rain, which the fitted world does \
         not model"
    )]
    Rain(usize),
    #[error("shot {0} is not a step of this world's moves and AoI update")]
    Foreign(usize),
    #[error(
        "shot {0} charges a cell and device another shot charged differently: the task's costs \
         are drawn (a risky region), which the fitted world does not model"
    )]
    Drawn(usize),
}

/// The world's form under `world` with no task in it: no rain, and a power weight of 1.
pub fn template(world: &WorldConfig) -> World {
    let task = TaskConfig {
        name: "fitted".into(),
        lambda: world.devices as f64,
        role: TaskRole::MetaTest,
        rain: None,
        rain_moves_every: None,
        risky: None,
        device_cells: None,
        layout_seed: None,
    };
    World::new(world, &task, 0)
}

/// The world `shots` identify under `world`'s form ([`template`]): its power costs fitted to
/// them. Nothing of the shots' task but the shots is read.
pub fn identify(world: &WorldConfig, shots: &[Transition]) -> Result<Identified, Unidentified> {
    if shots.is_empty() {
        return Err(Unidentified::NoShots);
    }
    let form = template(world);
    let seen = observed_costs(&form, shots)?;
    let k = form.devices();
    let largest = seen.iter().map(|&(_, cost)| cost).fold(0.0, f64::max);
    let tolerance = RESIDUAL_OF_COST * largest_cost(shots);
    let grid = form.grid_cells();
    let mut table = vec![largest; (grid * grid) as usize * k];
    let mut devices_fitted = 0;
    for device in 0..k {
        let points: Vec<(Cell, f64)> = seen
            .iter()
            .filter(|((_, d), _)| *d == device)
            .map(|&((cell, _), cost)| (cell, cost))
            .collect();
        let law = fit_law(&points, tolerance).or_else(|| locate(&form, &points, tolerance));
        if let Some(law) = law {
            devices_fitted += usize::from(law.determined());
            for c in 0..grid * grid {
                table[c as usize * k + device] = law.at((c % grid, c / grid));
            }
        }
    }
    for &((cell, device), cost) in &seen {
        table[(cell.1 * grid + cell.0) as usize * k + device] = cost;
    }
    Ok(Identified {
        world: form.with_power_table(table),
        devices_fitted,
    })
}

/// Each (cell, device) pair the shots schedule and the power cost it had.
/// Refused if a shot's next observation is not the one the form's moves and AoI update make
/// (with its transmission failed: rain; or at all), or if two shots charge one pair different
/// costs beyond the f32 rounding of their rewards (a risky region's drawn penalty).
fn observed_costs(form: &World, shots: &[Transition]) -> Result<Costs, Unidentified> {
    let mut next = vec![0u16; 2 + form.devices()];
    let mut seen = Costs::new();
    let mut outages = 0;
    for (i, t) in shots.iter().enumerate() {
        let action = usize::from(t.action);
        let makes = |outage: bool, next: &mut Vec<u16>| {
            form.outcome(&t.obs, action, outage, false, next).is_some() && *next == t.next_obs
        };
        if !makes(false, &mut next) {
            match makes(true, &mut next) {
                true => outages += 1,
                false => return Err(Unidentified::Foreign(i)),
            }
            continue;
        }
        let weighted: f64 = next[2..]
            .iter()
            .zip(form.delta())
            .map(|(&a, d)| d * f64::from(a))
            .sum();
        let key = (
            (u32::from(t.obs[0]), u32::from(t.obs[1])),
            form.layout().device(action),
        );
        let cost = -f64::from(t.reward) - weighted;
        match seen.iter().find(|(seen_key, _)| *seen_key == key) {
            None => seen.push((key, cost)),
            Some(&(_, was)) if (cost - was).abs() > 1e-4 * f64::from(t.reward).abs().max(1.0) => {
                return Err(Unidentified::Drawn(i))
            }
            Some(_) => {}
        }
    }
    match outages {
        0 => Ok(seen),
        n => Err(Unidentified::Rain(n)),
    }
}

fn largest_cost(shots: &[Transition]) -> f64 {
    shots
        .iter()
        .map(|t| -f64::from(t.reward))
        .fold(0.0, f64::max)
}

/// A device's power cost as a function of the cell.
enum Law {
    /// w . (x^2 + y^2, x, y, 1).
    Quadric(DVector<f64>),
    /// The largest of c (1 + s d^2) over the candidates (device cell, c), with d the distance in
    /// cells and s = (r / h)^2.
    Located {
        slant: f64,
        candidates: Vec<(Cell, f64)>,
    },
}

impl Law {
    fn features((x, y): Cell) -> [f64; 4] {
        let (x, y) = (f64::from(x), f64::from(y));
        [x * x + y * y, x, y, 1.0]
    }

    /// c's multiplier from `cell` for a device at `device`: 1 + s d^2.
    fn spread(slant: f64, cell: Cell, device: Cell) -> f64 {
        let dx = f64::from(cell.0) - f64::from(device.0);
        let dy = f64::from(cell.1) - f64::from(device.1);
        1.0 + slant * (dx * dx + dy * dy)
    }

    fn at(&self, cell: Cell) -> f64 {
        match self {
            Law::Quadric(w) => Self::features(cell)
                .iter()
                .zip(w.iter())
                .map(|(f, w)| f * w)
                .sum(),
            Law::Located { slant, candidates } => candidates
                .iter()
                .map(|&(device, c)| c * Self::spread(*slant, cell, device))
                .fold(0.0, f64::max),
        }
    }

    /// The shots leave one power for every cell.
    fn determined(&self) -> bool {
        match self {
            Law::Quadric(_) => true,
            Law::Located { candidates, .. } => candidates.len() == 1,
        }
    }

    fn passes(&self, points: &[(Cell, f64)], tolerance: f64) -> bool {
        points
            .iter()
            .all(|&(cell, power)| (self.at(cell) - power).abs() <= tolerance)
    }
}

/// The least-squares law through `points` (cell, cost), if their cells determine it (rank
/// 4) and it passes within `tolerance` of every point.
fn fit_law(points: &[(Cell, f64)], tolerance: f64) -> Option<Law> {
    if points.len() < 4 {
        return None;
    }
    let x = DMatrix::from_fn(points.len(), 4, |i, j| Law::features(points[i].0)[j]);
    let y = DVector::from_iterator(points.len(), points.iter().map(|p| p.1));
    let svd = x.svd(true, true);
    let eps = 1e-9 * svd.singular_values.max();
    if svd.rank(eps) < 4 {
        return None;
    }
    let law = Law::Quadric(svd.solve(&y, eps).ok()?);
    law.passes(points, tolerance).then_some(law)
}

/// The law of a device at one of the grid's cells through `points`: every cell whose
/// least-squares gain passes within `tolerance` of every point is a candidate. `None` if no cell
/// is, or the world's power term is not one device's law.
fn locate(form: &World, points: &[(Cell, f64)], tolerance: f64) -> Option<Law> {
    let slant = form.slant_per_cell2()?;
    if points.is_empty() {
        return None;
    }
    let grid = form.grid_cells();
    let candidates: Vec<(Cell, f64)> = (0..grid * grid)
        .map(|c| (c % grid, c / grid))
        .filter_map(|device| {
            let (mut fp, mut ff) = (0.0, 0.0);
            for &(cell, power) in points {
                let f = Law::spread(slant, cell, device);
                fp += f * power;
                ff += f * f;
            }
            let one = Law::Located {
                slant,
                candidates: vec![(device, fp / ff)],
            };
            one.passes(points, tolerance).then_some((device, fp / ff))
        })
        .collect();
    (!candidates.is_empty()).then_some(Law::Located { slant, candidates })
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::config::{Config, RainZone, TaskConfig};

    use super::*;
    use crate::rollout::record_step;
    use crate::world::Move;

    fn world(noise_dbm: f64, lambda: f64) -> (World, Config) {
        let mut config = Config::default();
        config.world.noise_dbm = noise_dbm;
        let task = TaskConfig {
            lambda,
            ..config.tasks[0].clone()
        };
        (World::new(&config.world, &task, 0), config)
    }

    /// The transitions of `actions` from `start`, as an actor records them.
    fn shots(world: &World, start: (u32, u32), actions: &[usize]) -> Vec<Transition> {
        let mut w = world.clone().with_start(start);
        actions.iter().map(|&a| record_step(&mut w, a)).collect()
    }

    /// A snake over the whole grid, row by row, serving device t mod K at step t: every device
    /// from ten cells, five of them on one column, so no circle holds them.
    fn lap(world: &World) -> Vec<Transition> {
        let (k, grid) = (world.devices(), world.grid_cells() as usize);
        let actions: Vec<usize> = (0..grid * grid)
            .map(|t| {
                let (row, along) = (t / grid, t % grid);
                let mv = match (along == grid - 1, row % 2) {
                    (true, _) => Move::North,
                    (false, 0) => Move::East,
                    (false, _) => Move::West,
                };
                world.layout().action(mv.index(), t % k)
            })
            .collect();
        shots(world, (0, 0), &actions)
    }

    fn returns_from_every_cell(world: &World, actions: &[usize]) -> Vec<f64> {
        let grid = world.grid_cells();
        (0..grid * grid)
            .map(|c| {
                let w = world.clone().with_start((c % grid, c / grid));
                -w.cost_of_actions(actions)
            })
            .collect()
    }

    #[test]
    fn shots_that_determine_every_device_identify_the_world_exactly() {
        for (noise, lambda) in [(-100.0, 300.0), (-90.0, 2000.0), (-100.0, 0.0)] {
            let (world, config) = world(noise, lambda);
            let identified = identify(&config.world, &lap(&world)).unwrap();
            assert_eq!(identified.devices_fitted, world.devices());
            let plan: Vec<usize> = (0..100)
                .map(|t| (t * 7) % world.layout().action_count())
                .collect();
            let truth = returns_from_every_cell(&world, &plan);
            let model = returns_from_every_cell(&identified.world, &plan);
            for (t, m) in truth.iter().zip(&model) {
                assert!((t - m).abs() < 1e-3 * t.abs(), "true {t}, identified {m}");
            }
        }
    }

    /// Asserts that `model` charges `world`'s power cost for `device` above `cell` (the rewards
    /// are f32).
    fn charges(model: &World, world: &World, cell: (u32, u32), device: usize, mw: f64) {
        let modelled = model.transmission_at(cell, device, None).0;
        let cost = world.power_weight() * mw;
        assert!(
            (modelled - cost).abs() < 1e-5 * cost.max(1.0),
            "{modelled} charged for {cost} above {cell:?}"
        );
    }

    fn every_cell(world: &World) -> impl Iterator<Item = (u32, u32)> {
        let grid = world.grid_cells();
        (0..grid * grid).map(move |c| (c % grid, c / grid))
    }

    #[test]
    fn a_device_seen_from_three_cells_of_a_line_is_located() {
        for (noise, lambda) in [(-100.0, 300.0), (-90.0, 2000.0)] {
            let (world, config) = world(noise, lambda);
            let k = world.devices();
            // Device 0 only, from three cells of a line: no quadric is determined, but only one
            // cell of the grid puts a device at those three distances.
            let east = Move::East.index() * k;
            let shots = shots(&world, (0, 0), &[east; 3]);
            let identified = identify(&config.world, &shots).unwrap();
            assert_eq!(identified.devices_fitted, 1);
            for cell in every_cell(&world) {
                let mw = world.transmission_at(cell, 0, None).0;
                charges(&identified.world, &world, cell, 0, mw);
            }
        }
    }

    #[test]
    fn a_device_seen_from_one_cell_is_charged_its_worst_place() {
        let (world, config) = world(-100.0, 300.0);
        let k = world.devices();
        let stay = Move::Hover.index() * k;
        let identified = identify(&config.world, &shots(&world, (4, 4), &[stay])).unwrap();
        assert_eq!(identified.devices_fitted, 0);
        let truth = |cell| world.power_weight() * world.transmission_at(cell, 0, None).0;
        let mw = world.transmission_at((4, 4), 0, None).0;
        charges(&identified.world, &world, (4, 4), 0, mw);
        // Wherever the device is, the model charges at least its cost, and somewhere more.
        let model = |cell| identified.world.transmission_at(cell, 0, None).0;
        assert!(every_cell(&world).all(|c| model(c) >= truth(c) * (1.0 - 1e-6)));
        assert!(every_cell(&world).any(|c| model(c) > truth(c) * 1.5));
    }

    #[test]
    fn a_device_no_law_explains_costs_the_largest_power_seen() {
        // Summed over the devices, the power is no single device's law: three cells of a line
        // determine no quadric, and no cell of the grid is a device's.
        let (_, mut config) = world(-100.0, 300.0);
        config.world.power_term = uavmeta_proto::config::PowerTerm::AllDevices;
        let task = TaskConfig {
            lambda: 300.0,
            ..config.tasks[0].clone()
        };
        let world = World::new(&config.world, &task, 0);
        let k = world.devices();
        let east = Move::East.index() * k;
        let identified = identify(&config.world, &shots(&world, (0, 0), &[east; 3])).unwrap();
        assert_eq!(identified.devices_fitted, 0);
        let seen = |cell| world.transmission_at(cell, 0, None).0;
        let largest = seen((0, 0)).max(seen((1, 0))).max(seen((2, 0)));
        // Where it was seen, its cost as seen; everywhere else the largest.
        charges(&identified.world, &world, (1, 0), 0, seen((1, 0)));
        charges(&identified.world, &world, (9, 9), 0, largest);
        charges(&identified.world, &world, (0, 0), 3, largest);
    }

    /// Rain is found from the shots alone: a lap through a rain zone has transmissions in
    /// outage, and the fit says so; the same lap without rain is identified.
    #[test]
    fn shots_with_an_outage_say_the_task_has_rain() {
        let (clear, config) = world(-100.0, 300.0);
        let task = TaskConfig {
            lambda: 300.0,
            rain: Some(RainZone {
                x0: 0,
                y0: 0,
                x1: 9,
                y1: 1,
            }),
            ..config.tasks[0].clone()
        };
        let rainy = World::new(&config.world, &task, 0);
        match identify(&config.world, &lap(&rainy)) {
            Err(Unidentified::Rain(n)) => assert!(n > 0),
            other => panic!("expected rain, got {other:?}"),
        }
        assert!(identify(&config.world, &lap(&clear)).is_ok());
    }

    #[test]
    fn shots_of_a_risky_region_identify_nothing() {
        let (_, config) = world(-100.0, 300.0);
        let risky = uavmeta_proto::config::RiskyRegion {
            x0: 0,
            y0: 0,
            x1: 9,
            y1: 9,
            penalty: 300.0,
            probability: 0.5,
        };
        let task = TaskConfig {
            risky: Some(risky),
            ..config.tasks[0].clone()
        };
        let world = World::new(&config.world, &task, 0);
        let hover = world.layout().action(Move::Hover.index(), 0);
        let shots = shots(&world, (4, 4), &[hover; 20]);
        match identify(&config.world, &shots) {
            Err(Unidentified::Drawn(i)) => assert!(i > 0),
            other => panic!("expected drawn costs, got {other:?}"),
        }
    }

    #[test]
    fn shots_the_model_does_not_make_identify_nothing() {
        let (world, config) = world(-100.0, 300.0);
        let mut shots = lap(&world);
        shots[3].next_obs[2] += 1;
        assert_eq!(
            identify(&config.world, &shots).unwrap_err(),
            Unidentified::Foreign(3)
        );
        assert_eq!(
            identify(&config.world, &[]).unwrap_err(),
            Unidentified::NoShots
        );
    }
}
