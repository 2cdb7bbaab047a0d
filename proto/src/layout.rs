//! The one observation and action layout every crate reads (docs/MODEL.md sections 1 and 11).
//!
//! One UAV's observation is its cell then every device's AoI, `[x, y, A_1 .. A_K]`; a team's
//! state is every UAV's cell then the AoI, `[x_1, y_1, .., x_U, y_U, A_1 .. A_K]`, so with one
//! UAV the state is the observation. Each UAV's action is a move and a target, numbered
//! `move * targets + target` over [`MOVES`], where the targets are the K devices and, with
//! `world.idle_action`, "none" (target K). The world, the datasets, the networks, the heuristics,
//! the planner, the exporters and the Python env all index through a [`Layout`] rather than
//! through `2 + K` or `move * K + device` of their own.
//!
//! ```
//! use uavmeta_proto::layout::Layout;
//! let layout = Layout::new(10);
//! assert_eq!((layout.observation_len(), layout.action_count()), (12, 50));
//! let action = layout.action(3, 7);
//! assert_eq!(layout.split(action), (3, 7));
//! let obs = [4u16, 5, 1, 2, 3, 1, 1, 1, 1, 1, 1, 9];
//! assert_eq!(Layout::cell(&obs), (4, 5));
//! assert_eq!(Layout::aoi(&obs)[9], 9);
//!
//! let team = Layout::team(10, 2, true);
//! assert_eq!((team.state_len(), team.action_count()), (14, 55));
//! assert_eq!(team.served(team.action(4, 10)), None);
//! let state = [4u16, 5, 0, 9, 1, 2, 3, 1, 1, 1, 1, 1, 1, 9];
//! assert_eq!(team.uav_cell(&state, 1), (0, 9));
//! let mut obs = [0u16; 12];
//! team.write_observation(&state, 1, &mut obs);
//! assert_eq!(obs, [0, 9, 1, 2, 3, 1, 1, 1, 1, 1, 1, 9]);
//! ```

use crate::config::MOVES;

/// Where a UAV's cell ends and the devices' AoI begins in one UAV's observation.
const CELL_LEN: usize = 2;

/// The layout of a world of `devices` devices and `uavs` UAVs, with or without the idle target.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    devices: usize,
    uavs: usize,
    idle: bool,
}

impl Layout {
    /// One UAV, no idle target: the paper's layout.
    #[inline]
    pub const fn new(devices: usize) -> Self {
        Self::team(devices, 1, false)
    }

    /// `uavs` UAVs over `devices` devices; `idle` adds the target "none" to every UAV's actions.
    #[inline]
    pub const fn team(devices: usize, uavs: usize, idle: bool) -> Self {
        Self {
            devices,
            uavs,
            idle,
        }
    }

    #[inline]
    pub fn devices(self) -> usize {
        self.devices
    }

    /// U.
    #[inline]
    pub fn uavs(self) -> usize {
        self.uavs
    }

    /// What one UAV can serve: the K devices, and "none" (target K) with the idle target.
    #[inline]
    pub fn targets(self) -> usize {
        self.devices + usize::from(self.idle)
    }

    /// Length of one UAV's observation: its cell, then K AoI values.
    #[inline]
    pub fn observation_len(self) -> usize {
        CELL_LEN + self.devices
    }

    /// Length of the team's state: every UAV's cell, then K AoI values.
    #[inline]
    pub fn state_len(self) -> usize {
        CELL_LEN * self.uavs + self.devices
    }

    /// Number of one UAV's discrete actions: five moves times its targets.
    #[inline]
    pub fn action_count(self) -> usize {
        MOVES.len() * self.targets()
    }

    /// The action that makes move `mv` (an index into [`MOVES`]) and serves `target` (a device,
    /// or K for none).
    #[inline]
    pub fn action(self, mv: usize, target: usize) -> usize {
        mv * self.targets() + target
    }

    /// The move (an index into [`MOVES`]) and the target of `action`.
    #[inline]
    pub fn split(self, action: usize) -> (usize, usize) {
        (action / self.targets(), action % self.targets())
    }

    /// The target `action` serves: a device, or K for none.
    #[inline]
    pub fn device(self, action: usize) -> usize {
        action % self.targets()
    }

    /// The device `action` serves, `None` for the idle target.
    #[inline]
    pub fn served(self, action: usize) -> Option<usize> {
        Some(self.device(action)).filter(|&d| d < self.devices)
    }

    /// UAV `u`'s cell in a team state.
    #[inline]
    pub fn uav_cell<T: Copy>(self, state: &[T], u: usize) -> (T, T) {
        (state[CELL_LEN * u], state[CELL_LEN * u + 1])
    }

    /// Writes UAV `u`'s cell into a team state.
    #[inline]
    pub fn set_uav_cell<T>(self, state: &mut [T], u: usize, (x, y): (T, T)) {
        state[CELL_LEN * u] = x;
        state[CELL_LEN * u + 1] = y;
    }

    /// Every device's AoI in a team state.
    #[inline]
    pub fn state_aoi<T>(self, state: &[T]) -> &[T] {
        &state[CELL_LEN * self.uavs..]
    }

    #[inline]
    pub fn state_aoi_mut<T>(self, state: &mut [T]) -> &mut [T] {
        &mut state[CELL_LEN * self.uavs..]
    }

    /// UAV `u`'s observation of a team state, `[x_u, y_u, A_1 .. A_K]`, into `out`.
    #[inline]
    pub fn write_observation<T: Copy>(self, state: &[T], u: usize, out: &mut [T]) {
        Self::set_cell(out, self.uav_cell(state, u));
        Self::aoi_mut(out).copy_from_slice(self.state_aoi(state));
    }

    /// The UAV's cell in an observation.
    #[inline]
    pub fn cell<T: Copy>(obs: &[T]) -> (T, T) {
        (obs[0], obs[1])
    }

    /// Writes the UAV's cell into an observation.
    #[inline]
    pub fn set_cell<T>(obs: &mut [T], (x, y): (T, T)) {
        obs[0] = x;
        obs[1] = y;
    }

    /// Every device's AoI in an observation, in device order.
    #[inline]
    pub fn aoi<T>(obs: &[T]) -> &[T] {
        &obs[CELL_LEN..]
    }

    #[inline]
    pub fn aoi_mut<T>(obs: &mut [T]) -> &mut [T] {
        &mut obs[CELL_LEN..]
    }
}
