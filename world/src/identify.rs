//! The world as a fine-tuning run's own shots identify it (docs/MODEL.md section 5, "Which network
//! a run keeps"): the moves, the AoI update and the reward's form are the model's, the power table
//! is fitted to the shots. Fine-tuning scores its candidate networks here, never in the true world.
//!
//! Each shot gives the power of one (cell, device) pair: the reward is -(sum_j delta_j A_j +
//! (lambda / K) P), with the AoI after the step in the next observation. By section 1's law a
//! device's power from cell (x, y) is c (h^2 + r^2 ((x - x_k)^2 + (y - y_k)^2)). Two fits, in turn:
//! - the law is linear in (x^2 + y^2, x, y, 1), so four cells not on one circle or line determine
//!   a device everywhere by least squares;
//! - else, since a device sits at a cell, each of the grid's cells is tried as the device's: the
//!   gain c is then the one unknown, and a cell whose law passes through every shot is a
//!   candidate. One candidate determines the device; several charge, at each cell, the largest
//!   power any of them gives.
//!
//! A device neither fit explains is charged the largest power the shots show from every cell it
//! was not seen at: a pessimistic model never favours a policy for going where the data has not
//! been.

use nalgebra::{DMatrix, DVector};
use uavmeta_proto::dataset::Transition;

use crate::world::World;

/// Residual a fit may leave, as a share of the largest step cost in the shots: the rewards are
/// f32, so a law that holds fits to about 1e-7 of the cost.
const RESIDUAL_OF_COST: f64 = 1e-4;

/// A grid cell, (x, y).
type Cell = (u32, u32);

/// The milliwatts of each (cell, device) pair the shots schedule, in the order the shots first
/// schedule it (the order of the least-squares rows).
type Powers = Vec<((Cell, usize), f64)>;

/// The identified world and how many devices the shots determine.
#[derive(Debug, Clone)]
pub struct Identified {
    /// `world` with the fitted power table.
    pub world: World,
    /// Devices whose power the shots determine everywhere (the others are pessimistic).
    pub devices_fitted: usize,
}

/// `world` (the true world of the shots' task, of which only the moves, the AoI update and the
/// reward's form are used) with its power table fitted to `shots`. `None` where the model cannot
/// hold: a task with rain, or a shot the model's dynamics do not make (an outage, another world).
pub fn identify(world: &World, shots: &[Transition]) -> Option<Identified> {
    if world.has_rain() || shots.is_empty() {
        return None;
    }
    let seen = observed_powers(world, shots)?;
    let k = world.devices();
    let largest = seen.iter().map(|&(_, mw)| mw).fold(0.0, f64::max);
    let tolerance =
        RESIDUAL_OF_COST * largest_cost(shots) / world.power_weight().max(f64::MIN_POSITIVE);
    let grid = world.grid_cells();
    let mut table = vec![largest; (grid * grid) as usize * k];
    let mut devices_fitted = 0;
    for device in 0..k {
        let points: Vec<(Cell, f64)> = seen
            .iter()
            .filter(|((_, d), _)| *d == device)
            .map(|&((cell, _), mw)| (cell, mw))
            .collect();
        let law = fit_law(&points, tolerance).or_else(|| locate(world, &points, tolerance));
        if let Some(law) = law {
            devices_fitted += usize::from(law.determined());
            for c in 0..grid * grid {
                table[c as usize * k + device] = law.at((c % grid, c / grid));
            }
        }
    }
    for &((cell, device), power) in &seen {
        table[(cell.1 * grid + cell.0) as usize * k + device] = power;
    }
    Some(Identified {
        world: world.with_power_table(table),
        devices_fitted,
    })
}

/// Each (cell, device) pair the shots schedule and the milliwatts it cost (the first shot's);
/// `None` if a shot's next observation is not the one the world's moves and AoI update make.
fn observed_powers(world: &World, shots: &[Transition]) -> Option<Powers> {
    let weight = world.power_weight();
    let mut next = vec![0u16; 2 + world.devices()];
    let mut seen = Powers::new();
    for t in shots {
        let action = usize::from(t.action);
        world.outcome(&t.obs, action, false, &mut next)?;
        if next != t.next_obs {
            return None;
        }
        let weighted: f64 = next[2..]
            .iter()
            .zip(world.delta())
            .map(|(&a, d)| d * f64::from(a))
            .sum();
        let power = match weight > 0.0 {
            true => (-f64::from(t.reward) - weighted) / weight,
            // lambda = 0: power never enters the reward, any table models it.
            false => 0.0,
        };
        let key = (
            (u32::from(t.obs[0]), u32::from(t.obs[1])),
            action % world.devices(),
        );
        if !seen.iter().any(|(seen_key, _)| *seen_key == key) {
            seen.push((key, power));
        }
    }
    Some(seen)
}

fn largest_cost(shots: &[Transition]) -> f64 {
    shots
        .iter()
        .map(|t| -f64::from(t.reward))
        .fold(0.0, f64::max)
}

/// A device's power as a function of the cell.
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

/// The least-squares law through `points` (cell, milliwatts), if their cells determine it (rank
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
fn locate(world: &World, points: &[(Cell, f64)], tolerance: f64) -> Option<Law> {
    let slant = world.slant_per_cell2()?;
    if points.is_empty() {
        return None;
    }
    let grid = world.grid_cells();
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
    use uavmeta_proto::config::{Config, TaskConfig};

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
                mv.index() * k + t % k
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
        for (noise, lambda) in [(-100.0, 300.0), (-90.0, 2000.0)] {
            let (world, _) = world(noise, lambda);
            let identified = identify(&world, &lap(&world)).unwrap();
            assert_eq!(identified.devices_fitted, world.devices());
            let plan: Vec<usize> = (0..100).map(|t| (t * 7) % world.action_count()).collect();
            let truth = returns_from_every_cell(&world, &plan);
            let model = returns_from_every_cell(&identified.world, &plan);
            for (t, m) in truth.iter().zip(&model) {
                assert!((t - m).abs() < 1e-3 * t.abs(), "true {t}, identified {m}");
            }
        }
    }

    /// Asserts that `model` charges `mw` for `device` above `cell` (the rewards are f32).
    fn charges(model: &World, cell: (u32, u32), device: usize, mw: f64) {
        let modelled = model.transmission_at(cell, device, None).0;
        assert!(
            (modelled - mw).abs() < 1e-5 * mw.max(1.0),
            "{modelled} mW for {mw} mW above {cell:?}"
        );
    }

    fn every_cell(world: &World) -> impl Iterator<Item = (u32, u32)> {
        let grid = world.grid_cells();
        (0..grid * grid).map(move |c| (c % grid, c / grid))
    }

    #[test]
    fn a_device_seen_from_three_cells_of_a_line_is_located() {
        for (noise, lambda) in [(-100.0, 300.0), (-90.0, 2000.0)] {
            let (world, _) = world(noise, lambda);
            let k = world.devices();
            // Device 0 only, from three cells of a line: no quadric is determined, but only one
            // cell of the grid puts a device at those three distances.
            let east = Move::East.index() * k;
            let identified = identify(&world, &shots(&world, (0, 0), &[east; 3])).unwrap();
            assert_eq!(identified.devices_fitted, 1);
            for cell in every_cell(&world) {
                charges(
                    &identified.world,
                    cell,
                    0,
                    world.transmission_at(cell, 0, None).0,
                );
            }
        }
    }

    #[test]
    fn a_device_seen_from_one_cell_is_charged_its_worst_place() {
        let (world, _) = world(-100.0, 300.0);
        let k = world.devices();
        let stay = Move::Hover.index() * k;
        let identified = identify(&world, &shots(&world, (4, 4), &[stay])).unwrap();
        assert_eq!(identified.devices_fitted, 0);
        let truth = |cell| world.transmission_at(cell, 0, None).0;
        charges(&identified.world, (4, 4), 0, truth((4, 4)));
        // Wherever the device is, the model charges at least its power, and somewhere more.
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
        let identified = identify(&world, &shots(&world, (0, 0), &[east; 3])).unwrap();
        assert_eq!(identified.devices_fitted, 0);
        let seen = |cell| world.transmission_at(cell, 0, None).0;
        let largest = seen((0, 0)).max(seen((1, 0))).max(seen((2, 0)));
        // Where it was seen, its power as seen; everywhere else the largest.
        charges(&identified.world, (1, 0), 0, seen((1, 0)));
        charges(&identified.world, (9, 9), 0, largest);
        charges(&identified.world, (0, 0), 3, largest);
    }

    #[test]
    fn shots_the_model_does_not_make_identify_nothing() {
        let (world, _) = world(-100.0, 300.0);
        let mut shots = lap(&world);
        shots[3].next_obs[2] += 1;
        assert!(identify(&world, &shots).is_none());
        assert!(identify(&world, &[]).is_none());
    }
}
