//! The one observation and action layout every crate reads (docs/MODEL.md section 1): an
//! observation is the UAV's cell then every device's AoI, `[x, y, A_1 .. A_K]`, and an action is
//! a move and a device, numbered `move * K + device` over [`MOVES`]. The world, the datasets, the
//! networks, the heuristics, the planner, the exporters and the Python env all index through a
//! [`Layout`] rather than through `2 + K` or `move * K + device` of their own.
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
//! ```

use crate::config::MOVES;

/// Where the UAV's cell ends and the devices' AoI begins in an observation.
const CELL_LEN: usize = 2;

/// The layout of a world of `devices` devices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    devices: usize,
}

impl Layout {
    #[inline]
    pub const fn new(devices: usize) -> Self {
        Self { devices }
    }

    #[inline]
    pub fn devices(self) -> usize {
        self.devices
    }

    /// Length of an observation: the UAV's cell, then K AoI values.
    #[inline]
    pub fn observation_len(self) -> usize {
        CELL_LEN + self.devices
    }

    /// Number of discrete actions: five moves times K devices.
    #[inline]
    pub fn action_count(self) -> usize {
        MOVES.len() * self.devices
    }

    /// The action that makes move `mv` (an index into [`MOVES`]) and serves `device`.
    #[inline]
    pub fn action(self, mv: usize, device: usize) -> usize {
        mv * self.devices + device
    }

    /// The move (an index into [`MOVES`]) and the device of `action`.
    #[inline]
    pub fn split(self, action: usize) -> (usize, usize) {
        (action / self.devices, action % self.devices)
    }

    /// The device `action` serves.
    #[inline]
    pub fn device(self, action: usize) -> usize {
        action % self.devices
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
