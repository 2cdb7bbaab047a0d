//! The planner reference: a beam search, knowing the world's dynamics, rewards and rain ahead, for
//! the best action sequence from the current state; the row every method's gap is read against.
//! The search, its cost-to-go h and when it is exact: docs/MODEL.md, section 9; its width and
//! weights b: docs/EXPERIMENTS.md, P and P2 (at b = 1 it fell 3% short on lambda-1000 and 11% on a
//! small world where serving out of order pays).
//!
//! **Cost.** Per step: width x 5K children of O(K) each plus a hash-map merge; memory:
//! width x (K + 2) u16 for the beam and width x T back-pointers. [`PlannerConfig::validate`]
//! refuses a width and horizon whose search would not fit in `planner.max_memory_mib`.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use uavmeta_proto::config::{PlannerConfig, RainZone};

use crate::rollout::Policy;
use crate::world::{Move, World};

/// A planned action sequence from a world's current state to its horizon.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Action indices `move * targets + target`, one per UAV per remaining step, step by step
    /// (UAV order within a step).
    pub actions: Vec<usize>,
    /// -sum of the rewards the world will give for `actions`.
    pub cost: f64,
}

/// The beam searches of docs/MODEL.md section 9, one per weight b of h's power part.
#[derive(Debug, Clone)]
pub struct Planner {
    beam_width: usize,
    /// b, the weights of h's power part.
    h_power_weights: Vec<f64>,
}

/// The nodes kept at one step, in structure-of-arrays form (one UAV's, or a team's).
#[derive(Debug, Default)]
pub(crate) struct Beam {
    /// UAV u of node i at `[i * U + u]`.
    pub(crate) cells: Vec<(u32, u32)>,
    /// A_1..A_K of node i at `[i * K..(i + 1) * K]`.
    pub(crate) aoi: Vec<u16>,
    /// Cost of the best path to each node.
    pub(crate) g: Vec<f64>,
}

/// One child of the expansion: node `parent` with action `action` (`move * targets + target`,
/// or a team's joint code); its cells are the parent's moved by the action.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Child {
    /// g + h, the ranking.
    pub(crate) score: f64,
    pub(crate) g: f64,
    /// Hash of the child's state; ties in score are broken by it.
    pub(crate) key: u64,
    pub(crate) parent: u32,
    pub(crate) action: u32,
    /// Index of the child's aged AoI vector in the expansion's scratch arena.
    pub(crate) aged: u32,
}

/// Where each kept node came from, per step, for reading the plan backwards.
pub(crate) type Trail = Vec<Vec<(u32, u32)>>;

impl Planner {
    /// A planner with `config`'s settings; the config must have passed `PlannerConfig::validate`.
    pub fn new(config: &PlannerConfig) -> Planner {
        Planner {
            beam_width: config.beam_width,
            h_power_weights: config.h_power_weights.clone(),
        }
    }

    /// The cheapest action sequence from `world`'s current state to its horizon: the beam
    /// searches' best ([`Planner::beam`]), then improved by local search over its device
    /// schedule with the exact cheapest path of each ([`crate::schedule`]).
    pub fn plan(&self, world: &World) -> Plan {
        let patience = self.beam_width / crate::schedule::BEAM_PER_KICK;
        crate::schedule::improve(world, self.beam(world), patience)
    }

    /// The cheapest action sequence the beam searches find (the first weight's on a tie); a
    /// team's is [`crate::team_planner`]'s search over joint states.
    pub fn beam(&self, world: &World) -> Plan {
        let reach = Reach::new(world);
        self.h_power_weights
            .iter()
            .map(|&b| match world.uavs() {
                1 => self.search(world, &reach, b),
                _ => crate::team_planner::search(world, &reach, self.beam_width, b),
            })
            .reduce(|best, plan| if plan.cost < best.cost { plan } else { best })
            .expect("planner.h_power_weights is not empty (PlannerConfig::validate)")
    }

    /// One beam search with weight `b` of h's power part.
    fn search(&self, world: &World, reach: &Reach, b: f64) -> Plan {
        let mut beam = Beam {
            cells: vec![world.uav()],
            aoi: world.aoi().to_vec(),
            g: vec![0.0],
        };
        let mut trail: Trail = Vec::new();
        for zone in world.rain_schedule() {
            let (next, from) = self.step(world, reach, b, &beam, zone);
            beam = next;
            trail.push(from);
        }
        let best = (0..beam.g.len())
            .min_by(|&a, &b| beam.g[a].total_cmp(&beam.g[b]))
            .unwrap_or(0);
        let cost = beam.g.get(best).copied().unwrap_or(0.0);
        Plan {
            actions: read_back(&trail, best),
            cost,
        }
    }

    /// One step of the search: every node expanded by every action, children merged by state,
    /// the best `beam_width` kept. Returns the new beam and each kept node's (parent, action).
    fn step(
        &self,
        world: &World,
        reach: &Reach,
        b: f64,
        beam: &Beam,
        zone: Option<RainZone>,
    ) -> (Beam, Vec<(u32, u32)>) {
        let (children, aged) = expand(world, reach, b, beam, zone);
        let k = world.devices();
        let cell_of = |c: &Child| {
            let (mv, _) = world.layout().split(c.action as usize);
            world.moved(beam.cells[c.parent as usize], Move::from_index(mv))
        };
        let same = |a: &Child, b: &Child| {
            let (x, y) = (a.aged as usize * k, b.aged as usize * k);
            cell_of(a) == cell_of(b) && aged[x..x + k] == aged[y..y + k]
        };
        let kept = keep_best(children, self.beam_width, same);
        let mut next = Beam::default();
        let mut from = Vec::with_capacity(kept.len());
        for c in &kept {
            next.cells.push(cell_of(c));
            let at = c.aged as usize * k;
            next.aoi.extend_from_slice(&aged[at..at + k]);
            next.g.push(c.g);
            from.push((c.parent, c.action));
        }
        (next, from)
    }
}

/// Every child of every node, and the scratch arena of aged AoI vectors they point into (one per
/// node and device: the move does not change the AoI).
fn expand(
    world: &World,
    reach: &Reach,
    h_power_weight: f64,
    beam: &Beam,
    zone: Option<RainZone>,
) -> (Vec<Child>, Vec<u16>) {
    let k = world.devices();
    let cap = world.aoi_max();
    let delta = world.delta();
    let mut aged = Vec::with_capacity(beam.g.len() * k * k);
    let mut children = Vec::with_capacity(beam.g.len() * k * 5);
    let mut due = DueOrder::new(k);
    for (i, &cell) in beam.cells.iter().enumerate() {
        let aoi = &beam.aoi[i * k..(i + 1) * k];
        // The devices, and "none" where the layout has it.
        for device in 0..world.layout().targets() {
            let slot = aged.len() / k;
            // docs/MODEL.md section 1, steps 1-4 for (cell, device).
            let (power_mw, outage) = world.transmission_at(cell, device, zone);
            aged.extend(aoi.iter().map(|&a| a.saturating_add(1).min(cap)));
            let vector = &mut aged[slot * k..];
            if !outage && device < k {
                vector[device] = 1;
            }
            let weighted: f64 = vector.iter().zip(delta).map(|(&a, &d)| d * a as f64).sum();
            let g = beam.g[i]
                + weighted
                + world.power_weight() * power_mw
                + world.expected_penalty_at(cell, device);
            let aoi_to_go = due.sort(vector, delta, 1);
            let aoi_key = hash_aoi(vector);
            for mv in Move::ALL {
                let next = world.moved(cell, mv);
                let power_to_go =
                    h_power_weight * world.power_weight() * reach.power_to_go(next, &due.order);
                children.push(Child {
                    score: g + aoi_to_go + power_to_go,
                    g,
                    key: mix(aoi_key, ((next.0 as u64) << 32) | next.1 as u64),
                    parent: i as u32,
                    action: world.layout().action(mv.index(), device) as u32,
                    aged: slot as u32,
                });
            }
        }
    }
    (children, aged)
}

/// The devices in the order stalest first would serve them, and the AoI part of h.
pub(crate) struct DueOrder {
    pub(crate) order: Vec<usize>,
    weighted: Vec<f64>,
}

impl DueOrder {
    pub(crate) fn new(k: usize) -> DueOrder {
        DueOrder {
            order: (0..k).collect(),
            weighted: vec![0.0; k],
        }
    }

    /// Orders the devices by delta A, largest first (ties to the lower index), and returns
    /// sum_i (i / U) (delta A)_(i), `uavs` = U devices served a step: the AoI cost of the next
    /// K / U steps under that order, up to a constant.
    pub(crate) fn sort(&mut self, aoi: &[u16], delta: &[f64], uavs: usize) -> f64 {
        for ((w, &a), &d) in self.weighted.iter_mut().zip(aoi).zip(delta) {
            *w = d * a as f64;
        }
        let weighted = &self.weighted;
        self.order
            .sort_unstable_by(|&a, &b| weighted[b].total_cmp(&weighted[a]).then(a.cmp(&b)));
        self.order
            .iter()
            .enumerate()
            .map(|(i, &j)| (i / uavs) as f64 * weighted[j])
            .sum()
    }
}

/// P_min: for every cell c, device j and distance d < K, the least clear-sky power of serving j
/// from a cell within d moves of c, at `[(c * K + j) * K + d]`.
pub(crate) struct Reach {
    grid: u32,
    k: usize,
    min_mw: Vec<f64>,
}

impl Reach {
    pub(crate) fn new(world: &World) -> Reach {
        let (grid, k) = (world.grid_cells(), world.devices());
        let cells = (grid * grid) as usize;
        let mut min_mw = vec![f64::INFINITY; cells * k * k];
        for c in 0..cells {
            let (cx, cy) = (c as u32 % grid, c as u32 / grid);
            for o in 0..cells {
                let (ox, oy) = (o as u32 % grid, o as u32 / grid);
                let distance = (cx.abs_diff(ox) + cy.abs_diff(oy)) as usize;
                for j in 0..k {
                    let mw = world.transmission_at((ox, oy), j, None).0;
                    let row = &mut min_mw[(c * k + j) * k..(c * k + j + 1) * k];
                    for best in row.iter_mut().skip(distance) {
                        *best = best.min(mw);
                    }
                }
            }
        }
        Reach { grid, k, min_mw }
    }

    /// sum_i P_min(cell, order[i], i): the power part of h, in milliwatts.
    fn power_to_go(&self, cell: (u32, u32), order: &[usize]) -> f64 {
        order
            .iter()
            .enumerate()
            .map(|(d, &j)| self.least_mw(cell, j, d))
            .sum()
    }

    /// P_min(cell, device, d).
    pub(crate) fn least_mw(&self, cell: (u32, u32), device: usize, d: usize) -> f64 {
        let c = (cell.1 * self.grid + cell.0) as usize;
        self.min_mw[(c * self.k + device) * self.k + d]
    }
}

/// The best `width` distinct states among `children` (`same` says whether two are one state),
/// each by its cheapest path, best first.
pub(crate) fn keep_best(
    mut children: Vec<Child>,
    width: usize,
    same: impl Fn(&Child, &Child) -> bool,
) -> Vec<Child> {
    // Copies of one state share h, so the best copy always ranks before the others: ranking
    // the children first and merging only the best 2 x width spares the merge most of them.
    let shortlist = 2 * width;
    if children.len() > shortlist {
        children.select_nth_unstable_by(shortlist - 1, rank);
        children.truncate(shortlist);
    }
    let mut kept = merge(children, same);
    if kept.len() > width {
        kept.select_nth_unstable_by(width - 1, rank);
        kept.truncate(width);
    }
    kept.sort_unstable_by(rank);
    kept
}

/// The children with one per state: the cheapest path to it (ties to the first expanded).
fn merge(children: Vec<Child>, same: impl Fn(&Child, &Child) -> bool) -> Vec<Child> {
    let mut index: HashMap<u64, u32, BuildHasherDefault<KeyHasher>> =
        HashMap::with_capacity_and_hasher(children.len(), Default::default());
    let mut kept: Vec<Child> = Vec::with_capacity(children.len());
    for child in children {
        // Open addressing over the 64-bit key: a true hash collision probes on.
        let mut key = child.key;
        loop {
            match index.get(&key) {
                None => {
                    index.insert(key, kept.len() as u32);
                    kept.push(child);
                    break;
                }
                Some(&at) if same(&kept[at as usize], &child) => {
                    if child.g < kept[at as usize].g {
                        kept[at as usize] = child;
                    }
                    break;
                }
                Some(_) => key = key.wrapping_add(1),
            }
        }
    }
    kept
}

/// The ranking: lower g + h first, then by state key and action, so the order is total and the
/// search deterministic.
fn rank(a: &Child, b: &Child) -> std::cmp::Ordering {
    a.score
        .total_cmp(&b.score)
        .then(a.key.cmp(&b.key))
        .then(a.parent.cmp(&b.parent))
        .then(a.action.cmp(&b.action))
}

/// The actions from the root to node `last` of the final beam (a team's as joint codes).
pub(crate) fn read_back(trail: &Trail, last: usize) -> Vec<usize> {
    let mut actions = vec![0; trail.len()];
    let mut node = last;
    for (t, from) in trail.iter().enumerate().rev() {
        let (parent, action) = from[node];
        actions[t] = action as usize;
        node = parent as usize;
    }
    actions
}

/// The hasher of the merge's map: its keys are already mixed 64-bit hashes, used as they are.
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 << 8) | b as u64;
        }
    }

    fn write_u64(&mut self, n: u64) {
        self.0 = n;
    }
}

/// FNV-1a over the AoI vector.
pub(crate) fn hash_aoi(aoi: &[u16]) -> u64 {
    fnv_words(aoi.iter().map(|&a| a as u64))
}

/// FNV-1a taken a word at a time (one multiply per word, not per byte): the planner's state keys.
pub(crate) fn fnv_words(words: impl IntoIterator<Item = u64>) -> u64 {
    words.into_iter().fold(0xcbf2_9ce4_8422_2325, |h, w| {
        (h ^ w).wrapping_mul(0x0100_0000_01b3)
    })
}

/// SplitMix64's finaliser over two words.
pub(crate) fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The planner as a policy: at the first step of an episode it plans to the horizon from the
/// world's state (the world it is handed, which is the true one: it reads the rain schedule
/// from it), then plays the plan. A world whose state leaves the plan (another policy stepped
/// it) is planned for again from where it stands. [`PlannerPolicy::in_model`] plans in a model
/// of the world instead, from the state the true world shows.
#[derive(Debug, Clone)]
pub struct PlannerPolicy {
    planner: Planner,
    /// The world it plans in, if not the one it acts in.
    model: Option<World>,
    plan: Vec<usize>,
    /// The step of the episode `plan[0]` is for.
    from_t: u32,
    /// The UAV's cell and AoI the plan expects at each step, to notice a world that left it.
    expected: Vec<u16>,
}

impl PlannerPolicy {
    pub fn new(config: &PlannerConfig) -> PlannerPolicy {
        PlannerPolicy {
            planner: Planner::new(config),
            model: None,
            plan: Vec::new(),
            from_t: 0,
            expected: Vec::new(),
        }
    }

    /// The planner planning in `model` (the world a run's shots identify,
    /// `crate::identify`): at each replan `model` is put in the state the true world shows, and
    /// the plan and the observations it expects are the model's.
    pub fn in_model(config: &PlannerConfig, model: World) -> PlannerPolicy {
        PlannerPolicy {
            model: Some(model),
            ..PlannerPolicy::new(config)
        }
    }

    /// The state the plan expects at step `t`, if it covers it.
    fn expected_at(&self, t: u32, len: usize) -> Option<&[u16]> {
        let i = t.checked_sub(self.from_t)? as usize;
        (i * len < self.expected.len()).then(|| &self.expected[i * len..(i + 1) * len])
    }

    /// Plans from `world`'s state (in the model, if it has one) and records the states the plan
    /// will meet.
    fn replan(&mut self, world: &World) {
        let mut ahead = match &self.model {
            Some(model) => {
                let mut model = model.clone();
                model.set_observation(world.observation());
                model.set_t(world.t());
                model
            }
            None => world.clone(),
        };
        let plan = self.planner.plan(&ahead);
        self.expected.clear();
        for step in plan.actions.chunks(world.uavs()) {
            self.expected.extend_from_slice(ahead.observation());
            ahead.step_team(step);
        }
        self.plan = plan.actions;
        self.from_t = world.t();
    }

    /// Every UAV's action at the world's step, planning first at an episode's start (new start,
    /// new rain draws) or where the world left the plan.
    fn actions(&mut self, world: &World) -> &[usize] {
        let len = world.observation().len();
        if world.t() == 0 || self.expected_at(world.t(), len) != Some(world.observation()) {
            self.replan(world);
        }
        let uavs = world.uavs();
        let i = (world.t() - self.from_t) as usize * uavs;
        &self.plan[i..i + uavs]
    }
}

impl Policy for PlannerPolicy {
    fn act(&mut self, world: &World) -> usize {
        self.actions(world)[0]
    }

    fn act_team(&mut self, world: &World, actions: &mut [usize]) {
        actions.copy_from_slice(self.actions(world));
    }

    fn acts_for_teams(&self) -> bool {
        true
    }
}
