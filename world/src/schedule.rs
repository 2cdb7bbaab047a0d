//! Local improvement of a plan's device schedule, each schedule flown by its exact cheapest path
//! (the search: docs/MODEL.md, section 9, "Schedule search"). `F[t][c]`, the least power cost of
//! steps 0..t arriving at cell c at step t, and `B[t][c]`, the least from cell c at step t to the
//! end, price a change of one step's device, or a swap of two neighbouring steps', in O(cells)
//! against the whole schedule's O(T x cells); the AoI part of a change is priced from the two
//! devices' service steps.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::planner::{fnv_words, Plan};
use crate::world::{Move, World};

/// Sweeps over the schedule at most: each costs about (T x K) x cells operations.
pub const MAX_SWEEPS: usize = 50;

/// States of the beam per kick of patience: `planner.beam_width` sets the effort of both
/// searches. Each kick redraws [`KICK_WIDTH`] neighbouring steps' devices of the best schedule so
/// far and descends again; the kicks stop once `planner.beam_width` / 4 of them in a row (64 at the
/// default 256, 4 for a quick run's 16) have found nothing cheaper, or after
/// [`MAX_KICKS_PER_PATIENCE`] times that many. Where power dominates a fixed 32 kicks stopped well
/// short of where the search converges (docs/EXPERIMENTS.md, P6): on lambda-300 at -90 dBm 32 kicks
/// reached -11 676, stopping on 64 in a row -11 562.
pub const BEAM_PER_KICK: usize = 4;

/// The most kicks of one improvement, as a multiple of its patience: a bound on its cost (on the
/// measured tasks it stopped after 89 to 476 kicks at the default patience of 64).
pub const MAX_KICKS_PER_PATIENCE: usize = 16;

/// Steps whose devices a kick redraws.
const KICK_WIDTH: usize = 8;

/// A hash of the world's state, the seed of the kicks: a plan stays a function of the state.
fn state_key(world: &World) -> u64 {
    let (x, y) = world.uav();
    fnv_words(
        [x as u64, y as u64, world.t() as u64]
            .into_iter()
            .chain(world.aoi().iter().map(|&a| a as u64)),
    )
}

/// `plan` improved by the schedule search (docs/MODEL.md section 9), kicking until `patience` kicks
/// in a row find nothing cheaper, if `world` (at its current state) has no rain ahead; otherwise,
/// or if nothing improves, `plan` itself.
pub fn improve(world: &World, plan: Plan, patience: usize) -> Plan {
    // A schedule of devices only: "none" (`world.idle_action`) and teams keep the beam's plan.
    let one_uav_of_devices = world.uavs() == 1 && world.layout().targets() == world.devices();
    if world.rain_schedule().iter().any(Option::is_some)
        || plan.actions.is_empty()
        || !one_uav_of_devices
    {
        return plan;
    }
    let layout = world.layout();
    let grid = Grid::new(world);
    let devices = plan.actions.iter().map(|&a| layout.device(a)).collect();
    let mut best = Schedule::new(&grid, devices);
    best.descend();
    let mut rng = ChaCha8Rng::seed_from_u64(state_key(world));
    let steps = best.devices.len();
    let mut since_gain = 0;
    for _ in 0..patience * MAX_KICKS_PER_PATIENCE {
        if since_gain == patience {
            break;
        }
        let mut devices = best.devices.clone();
        let width = KICK_WIDTH.min(steps);
        let from = rng.random_range(0..=steps - width);
        for d in &mut devices[from..from + width] {
            *d = rng.random_range(0..layout.devices());
        }
        let mut trial = Schedule::new(&grid, devices);
        trial.descend();
        if trial.total() < best.total() - 1e-9 * best.total().abs() {
            best = trial;
            since_gain = 0;
        } else {
            since_gain += 1;
        }
    }
    let actions = best.actions();
    let cost = world.cost_of_actions(&actions);
    if cost < plan.cost {
        Plan { actions, cost }
    } else {
        plan
    }
}

/// The world's grid as the paths see it, made once for all the schedules of one improvement.
struct Grid<'w> {
    world: &'w World,
    /// Cells, row-major; `next[c]` are the cells one move from c, in move order.
    cells: usize,
    next: Vec<[usize; 5]>,
    start: usize,
    /// lambda / K times the clear-sky power of serving device j from cell c, plus the risky
    /// region's expected penalty there, at `[j * cells + c]`.
    power: Vec<f64>,
}

impl<'w> Grid<'w> {
    fn new(world: &'w World) -> Self {
        let l = world.grid_cells();
        let index = |(x, y): (u32, u32)| (y * l + x) as usize;
        let cells = (l * l) as usize;
        let next = (0..cells)
            .map(|c| std::array::from_fn(|m| index(world.moved(cell(l, c), Move::from_index(m)))))
            .collect();
        let power = (0..world.devices())
            .flat_map(|j| {
                (0..cells).map(move |c| {
                    world.power_weight() * world.transmission_at(cell(l, c), j, None).0
                        + world.expected_penalty_at(cell(l, c), j)
                })
            })
            .collect();
        Grid {
            world,
            cells,
            next,
            start: index(world.uav()),
            power,
        }
    }

    /// The power costs of serving `device`, by cell.
    fn power_of(&self, device: usize) -> &[f64] {
        &self.power[device * self.cells..][..self.cells]
    }

    /// `row` (the cheapest costs from step t + 1 on, by cell) moved back over step t serving
    /// `device`: B's recursion.
    fn back_over(&self, device: usize, row: &[f64], out: &mut [f64]) {
        for ((o, next), power) in out.iter_mut().zip(&self.next).zip(self.power_of(device)) {
            let onward = next.iter().map(|&to| row[to]).fold(f64::INFINITY, f64::min);
            *o = power + onward;
        }
    }
}

/// A device schedule from the world's state, with its tables of cheapest paths.
struct Schedule<'g> {
    grid: &'g Grid<'g>,
    devices: Vec<usize>,
    /// `F[t * cells + c]` and `B[t * cells + c]` (module doc); `B` has T + 1 rows. While a sweep
    /// runs, F is valid up to row `forward_rows` and B only from the sweep's step on (a change
    /// at step t alters F after t and B up to t).
    forward: Vec<f64>,
    forward_rows: usize,
    backward: Vec<f64>,
    /// The steps at which each device is served, ascending.
    served: Vec<Vec<usize>>,
}

impl<'g> Schedule<'g> {
    fn new(grid: &'g Grid<'g>, devices: Vec<usize>) -> Self {
        let mut s = Schedule {
            grid,
            devices,
            forward: Vec::new(),
            forward_rows: 0,
            backward: Vec::new(),
            served: Vec::new(),
        };
        s.tabulate();
        s
    }

    /// The world the grid was made from.
    fn world(&self) -> &'g World {
        self.grid.world
    }

    /// F and B of the current schedule, whole.
    fn tabulate(&mut self) {
        let (n, t_max) = (self.grid.cells, self.devices.len());
        self.forward = vec![f64::INFINITY; (t_max + 1) * n];
        self.forward[self.grid.start] = 0.0;
        self.forward_rows = 0;
        self.extend_forward(t_max);
        let mut backward = vec![0.0; (t_max + 1) * n];
        for t in (0..t_max).rev() {
            let (here, onward) = backward[t * n..].split_at_mut(n);
            self.grid.back_over(self.devices[t], &onward[..n], here);
        }
        self.backward = backward;
        self.index_services();
    }

    /// F's rows up to `row`, from the last valid one.
    fn extend_forward(&mut self, row: usize) {
        let n = self.grid.cells;
        for t in self.forward_rows..row {
            let (done, rest) = self.forward.split_at_mut((t + 1) * n);
            let next_row = &mut rest[..n];
            next_row.fill(f64::INFINITY);
            let power = self.grid.power_of(self.devices[t]);
            for (c, &here) in done[t * n..].iter().enumerate() {
                if here.is_finite() {
                    let cost = here + power[c];
                    for &to in &self.grid.next[c] {
                        next_row[to] = next_row[to].min(cost);
                    }
                }
            }
        }
        self.forward_rows = self.forward_rows.max(row);
    }

    /// `served` from `devices`.
    fn index_services(&mut self) {
        let mut served = vec![Vec::new(); self.world().devices()];
        for (t, &device) in self.devices.iter().enumerate() {
            served[device].push(t);
        }
        self.served = served;
    }

    /// Device j's AoI cost over the horizon when served at the ascending steps `times`: from its
    /// age now until its first service, then 1, 2, .. after each (capped at A_max).
    fn device_cost(&self, j: usize, times: impl Iterator<Item = usize>) -> f64 {
        let cap = u64::from(self.world().aoi_max());
        // The sum of min(from + i, cap) over i < n.
        let ages = |from: u64, n: u64| {
            let below = if from > cap {
                0
            } else {
                (cap - from + 1).min(n)
            };
            below * from + below * below.saturating_sub(1) / 2 + (n - below) * cap
        };
        let now = u64::from(self.world().aoi()[j]);
        let (mut sum, mut last) = (0, None);
        for t in times.chain(std::iter::once(self.devices.len())) {
            sum += match last {
                None => ages(now + 1, t as u64),
                Some(s) => ages(1, (t - s) as u64),
            };
            last = Some(t);
        }
        self.world().delta()[j] * sum as f64
    }

    /// How much the AoI cost changes with `devices[t..t + with.len()]` replaced by `with`: only
    /// the devices served in that window before or after change.
    fn aoi_change(&self, t: usize, with: &[usize]) -> f64 {
        let end = t + with.len();
        let mut changed: Vec<usize> = self.devices[t..end].iter().chain(with).copied().collect();
        changed.sort_unstable();
        changed.dedup();
        changed
            .into_iter()
            .map(|j| {
                let times = &self.served[j];
                let before = times.iter().copied().filter(|&s| s < t);
                let inside = (t..end).filter(|&s| with[s - t] == j);
                let after = times.iter().copied().filter(|&s| s >= end);
                self.device_cost(j, before.chain(inside).chain(after))
                    - self.device_cost(j, times.iter().copied())
            })
            .sum()
    }

    /// The least power cost of the whole schedule with `devices[t..t + with.len()]` replaced by
    /// `with` (one or two steps).
    fn power_with(&self, t: usize, with: &[usize]) -> f64 {
        let n = self.grid.cells;
        // From the end of the replaced steps back to step t: the cheapest cost-to-go of each cell.
        let mut to_go = self.backward[(t + with.len()) * n..][..n].to_vec();
        let mut scratch = vec![0.0; n];
        for &device in with.iter().rev() {
            self.grid.back_over(device, &to_go, &mut scratch);
            std::mem::swap(&mut to_go, &mut scratch);
        }
        self.forward[t * n..][..n]
            .iter()
            .zip(&to_go)
            .map(|(f, b)| f + b)
            .fold(f64::INFINITY, f64::min)
    }

    /// The AoI cost of `devices` from the world's state (no rain: every transmission succeeds).
    fn aoi_cost(&self, devices: &[usize]) -> f64 {
        let cap = self.world().aoi_max();
        let delta = self.world().delta();
        let mut aoi = self.world().aoi().to_vec();
        let mut cost = 0.0;
        for &served in devices {
            for a in aoi.iter_mut() {
                *a = a.saturating_add(1).min(cap);
            }
            aoi[served] = 1;
            cost += aoi
                .iter()
                .zip(delta)
                .map(|(&a, &d)| d * f64::from(a))
                .sum::<f64>();
        }
        cost
    }

    /// Sweeps until one keeps nothing, at most [`MAX_SWEEPS`].
    fn descend(&mut self) {
        for _ in 0..MAX_SWEEPS {
            if !self.sweep() {
                break;
            }
        }
    }

    /// The schedule's cost along its cheapest path.
    fn total(&self) -> f64 {
        self.aoi_cost(&self.devices) + self.power_with(0, &[])
    }

    /// One pass over every single-step change and neighbouring swap; true if one was kept.
    fn sweep(&mut self) -> bool {
        let k = self.world().devices();
        let mut current_aoi = self.aoi_cost(&self.devices);
        let mut best = current_aoi + self.power_with(0, &[]);
        let mut improved = false;
        for t in 0..self.devices.len() {
            self.extend_forward(t);
            let mut candidates: Vec<Vec<usize>> = (0..k)
                .filter(|&d| d != self.devices[t])
                .map(|d| vec![d])
                .collect();
            if t + 1 < self.devices.len() && self.devices[t] != self.devices[t + 1] {
                candidates.push(vec![self.devices[t + 1], self.devices[t]]);
            }
            for with in candidates {
                let aoi = self.aoi_change(t, &with);
                let total = current_aoi + aoi + self.power_with(t, &with);
                // A margin against float noise: a change must gain, not tie.
                if total < best - 1e-9 * best.abs() {
                    best = total;
                    current_aoi += aoi;
                    self.devices[t..t + with.len()].copy_from_slice(&with);
                    self.index_services();
                    // F's rows after t are stale; B's from t + with.len() on are not, and are
                    // all the rest of the sweep reads.
                    self.forward_rows = t;
                    improved = true;
                }
            }
        }
        if improved {
            self.tabulate();
        }
        improved
    }

    /// The schedule's actions along its cheapest path (the first cheapest move on a tie).
    fn actions(&self) -> Vec<usize> {
        let (n, layout) = (self.grid.cells, self.world().layout());
        let next = &self.grid.next;
        let mut c = self.grid.start;
        let mut actions = Vec::with_capacity(self.devices.len());
        for (t, &device) in self.devices.iter().enumerate() {
            let m = (0..5)
                .min_by(|&a, &b| {
                    let cost = |m: usize| self.backward[(t + 1) * n + next[c][m]];
                    cost(a).total_cmp(&cost(b))
                })
                .expect("five moves");
            actions.push(layout.action(m, device));
            c = next[c][m];
        }
        actions
    }
}

/// Cell `c` (row-major index) of an `l x l` grid as `(x, y)`.
fn cell(l: u32, c: usize) -> (u32, u32) {
    ((c as u32) % l, (c as u32) / l)
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::config::{Config, TaskConfig};

    use super::*;

    /// The per-device AoI sums and their changes equal the step-by-step simulation, with an AoI
    /// cap that binds and unequal weights.
    #[test]
    fn the_aoi_changes_equal_the_simulation() {
        let text = "[world]\ngrid_cells = 3\ndevices = 3\nhorizon = 30\naoi_max = 7\ndelta = [1.0, 2.5, 0.5]\n";
        let cfg = Config::from_toml_str(text, "test", &[]).expect("config");
        let world = World::new(&cfg.world, &TaskConfig::one_off(500.0, None), 1);
        let devices: Vec<usize> = (0..30).map(|t| (t * t + t / 3) % 3).collect();
        let grid = Grid::new(&world);
        let schedule = Schedule::new(&grid, devices.clone());
        let total: f64 = (0..3)
            .map(|j| schedule.device_cost(j, schedule.served[j].iter().copied()))
            .sum();
        assert!((total - schedule.aoi_cost(&devices)).abs() < 1e-9);
        for (t, with) in [(0, vec![2]), (13, vec![0]), (28, vec![1, 0]), (29, vec![1])] {
            let mut changed = devices.clone();
            changed[t..t + with.len()].copy_from_slice(&with);
            let expected = schedule.aoi_cost(&changed) - schedule.aoi_cost(&devices);
            assert!(
                (schedule.aoi_change(t, &with) - expected).abs() < 1e-9,
                "{t} {with:?}"
            );
        }
    }
}
