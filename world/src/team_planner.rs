//! The planner reference for a team (docs/MODEL.md section 11): the beam search of
//! [`crate::planner`] over joint states, every UAV's cell and the shared AoI. Each node is
//! expanded by every joint action (each UAV's target, then each UAV's move), the children merged
//! by state and the best `planner.beam_width` kept. Its cost-to-go h is the one-UAV search's with
//! U services a step: the i-th device of the stalest-first order is served at step i / U, each from
//! whichever UAV can reach the cheaper cell by then.
//!
//! With "none" among the targets (`world.idle_action`) two UAVs never serve one device: one of
//! them idling restarts the same ages for less power. Without it they may, as the power term can
//! make the nearest device the cheapest for both.
//!
//! **Cost.** Per step: width x (5 x targets)^U children of O(U K) each, and width x targets^U aged
//! AoI vectors; `PlannerConfig::memory_bytes` counts them, so a team too large to search is
//! refused up front.

use uavmeta_proto::config::{RainZone, MAX_UAVS};

use crate::planner::{hash_aoi, keep_best, mix, read_back, Beam, Child, DueOrder, Plan, Reach};
use crate::world::{Move, World};

/// The moves of one UAV.
const MOVE_COUNT: usize = Move::ALL.len();

/// The joint actions of a team as codes: U digits in base `targets` for the targets, U in base 5
/// for the moves.
#[derive(Debug, Clone, Copy)]
struct Joint {
    uavs: usize,
    targets: usize,
    /// 5^U.
    move_codes: usize,
}

impl Joint {
    fn new(world: &World) -> Joint {
        let uavs = world.uavs();
        Joint {
            uavs,
            targets: world.layout().targets(),
            move_codes: MOVE_COUNT.pow(uavs as u32),
        }
    }

    fn target_codes(self) -> usize {
        self.targets.pow(self.uavs as u32)
    }

    /// The U digits of `code` in `base`, UAV 0's the most significant.
    fn digits(self, mut code: usize, base: usize) -> [usize; MAX_UAVS] {
        let mut out = [0; MAX_UAVS];
        for u in (0..self.uavs).rev() {
            out[u] = code % base;
            code /= base;
        }
        out
    }

    /// Every UAV's action index of joint code `action`.
    fn actions(self, world: &World, action: usize) -> impl Iterator<Item = usize> {
        let targets = self.digits(action / self.move_codes, self.targets);
        let moves = self.digits(action % self.move_codes, MOVE_COUNT);
        let layout = world.layout();
        (0..self.uavs).map(move |u| layout.action(moves[u], targets[u]))
    }
}

/// One beam search with weight `b` of h's power part, from `world`'s state to its horizon.
pub(crate) fn search(world: &World, reach: &Reach, beam_width: usize, b: f64) -> Plan {
    let joint = Joint::new(world);
    let mut beam = Beam {
        cells: (0..joint.uavs).map(|u| world.uav_cell(u)).collect(),
        aoi: world.aoi().to_vec(),
        g: vec![0.0],
    };
    let mut trail = Vec::new();
    for zone in world.rain_schedule() {
        let (next, from) = step(world, reach, joint, b, beam_width, &beam, zone);
        beam = next;
        trail.push(from);
    }
    let best = (0..beam.g.len())
        .min_by(|&x, &y| beam.g[x].total_cmp(&beam.g[y]))
        .unwrap_or(0);
    Plan {
        actions: read_back(&trail, best)
            .into_iter()
            .flat_map(|code| joint.actions(world, code))
            .collect(),
        cost: beam.g.get(best).copied().unwrap_or(0.0),
    }
}

/// One step of the search: every node expanded by every joint action, children merged by state,
/// the best `width` kept. Returns the new beam and each kept node's (parent, joint action).
fn step(
    world: &World,
    reach: &Reach,
    joint: Joint,
    b: f64,
    width: usize,
    beam: &Beam,
    zone: Option<RainZone>,
) -> (Beam, Vec<(u32, u32)>) {
    let (children, aged) = expand(world, reach, joint, b, beam, zone);
    let (k, uavs) = (world.devices(), joint.uavs);
    let cells_of = |c: &Child| next_cells(world, joint, &beam.cells, c);
    let same = |x: &Child, y: &Child| {
        let (i, j) = (x.aged as usize * k, y.aged as usize * k);
        aged[i..i + k] == aged[j..j + k] && cells_of(x)[..uavs] == cells_of(y)[..uavs]
    };
    let kept = keep_best(children, width, same);
    let mut next = Beam::default();
    let mut from = Vec::with_capacity(kept.len());
    for c in &kept {
        next.cells.extend_from_slice(&cells_of(c)[..uavs]);
        let at = c.aged as usize * k;
        next.aoi.extend_from_slice(&aged[at..at + k]);
        next.g.push(c.g);
        from.push((c.parent, c.action));
    }
    (next, from)
}

/// Every UAV's cell after child `c`'s moves.
fn next_cells(
    world: &World,
    joint: Joint,
    cells: &[(u32, u32)],
    c: &Child,
) -> [(u32, u32); MAX_UAVS] {
    let moves = joint.digits(c.action as usize % joint.move_codes, MOVE_COUNT);
    let from = &cells[c.parent as usize * joint.uavs..][..joint.uavs];
    let mut out = [(0, 0); MAX_UAVS];
    for (u, &cell) in from.iter().enumerate() {
        out[u] = world.moved(cell, Move::from_index(moves[u]));
    }
    out
}

/// Every child of every node, and the scratch arena of aged AoI vectors they point into (one per
/// node and joint target: the moves do not change the AoI).
fn expand(
    world: &World,
    reach: &Reach,
    joint: Joint,
    h_power_weight: f64,
    beam: &Beam,
    zone: Option<RainZone>,
) -> (Vec<Child>, Vec<u16>) {
    let (k, uavs) = (world.devices(), joint.uavs);
    let cap = world.aoi_max();
    let delta = world.delta();
    let idle = joint.targets > k;
    let mut aged = Vec::new();
    let mut children = Vec::new();
    let mut due = DueOrder::new(k);
    // Per UAV and move, P_min of each due position from the cell the move leads to.
    let mut reachable = vec![0.0; uavs * MOVE_COUNT * k];
    for i in 0..beam.g.len() {
        let cells = &beam.cells[i * uavs..(i + 1) * uavs];
        let aoi = &beam.aoi[i * k..(i + 1) * k];
        for code in 0..joint.target_codes() {
            let targets = joint.digits(code, joint.targets);
            let targets = &targets[..uavs];
            if idle && serves_one_device_twice(targets, k) {
                continue;
            }
            let slot = aged.len() / k;
            aged.extend(aoi.iter().map(|&a| a.saturating_add(1).min(cap)));
            let vector = &mut aged[slot * k..];
            // docs/MODEL.md section 11: each UAV transmits from its cell, the ages restart once.
            let mut cost = 0.0;
            for (&cell, &target) in cells.iter().zip(targets) {
                let (power_mw, outage) = world.transmission_at(cell, target, zone);
                cost += world.power_weight() * power_mw + world.expected_penalty_at(cell, target);
                if !outage && target < k {
                    vector[target] = 1;
                }
            }
            let weighted: f64 = vector.iter().zip(delta).map(|(&a, &d)| d * a as f64).sum();
            let g = beam.g[i] + weighted + cost;
            let aoi_to_go = due.sort(vector, delta, uavs);
            let aoi_key = hash_aoi(vector);
            fill_reachable(world, reach, cells, &due.order, &mut reachable);
            for moves in 0..joint.move_codes {
                let digits = joint.digits(moves, MOVE_COUNT);
                let mut key = aoi_key;
                for (u, &cell) in cells.iter().enumerate() {
                    let next = world.moved(cell, Move::from_index(digits[u]));
                    key = mix(key, ((next.0 as u64) << 32) | next.1 as u64);
                }
                let power_to_go = (0..k)
                    .map(|d| {
                        (0..uavs)
                            .map(|u| reachable[(u * MOVE_COUNT + digits[u]) * k + d])
                            .fold(f64::INFINITY, f64::min)
                    })
                    .sum::<f64>();
                children.push(Child {
                    score: g + aoi_to_go + h_power_weight * world.power_weight() * power_to_go,
                    g,
                    key,
                    parent: i as u32,
                    action: (code * joint.move_codes + moves) as u32,
                    aged: slot as u32,
                });
            }
        }
    }
    (children, aged)
}

/// Whether two UAVs of `targets` serve one device.
fn serves_one_device_twice(targets: &[usize], k: usize) -> bool {
    targets
        .iter()
        .enumerate()
        .any(|(u, &t)| t < k && targets[..u].contains(&t))
}

/// `out[(u * 5 + m) * K + d]` = P_min(cell UAV u reaches by move m, order[d], d / U): the least
/// power of serving the d-th due device from there at its turn.
fn fill_reachable(
    world: &World,
    reach: &Reach,
    cells: &[(u32, u32)],
    order: &[usize],
    out: &mut [f64],
) {
    let (k, uavs) = (order.len(), cells.len());
    for (u, &cell) in cells.iter().enumerate() {
        for mv in Move::ALL {
            let next = world.moved(cell, mv);
            let row = &mut out[(u * MOVE_COUNT + mv.index()) * k..][..k];
            for (d, (slot, &j)) in row.iter_mut().zip(order).enumerate() {
                *slot = reach.least_mw(next, j, d / uavs);
            }
        }
    }
}
