//! Episode metrics (docs/MODEL.md section 1) and their Monte-Carlo summaries: what rollouts,
//! training tables, the evaluator's CSV rows and its Prometheus gauges all report.

use serde::{Deserialize, Serialize};

/// One episode's figures.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct EpisodeMetrics {
    /// Sum of rewards.
    pub ret: f64,
    /// Mean over steps and devices of A_j after the AoI update.
    pub aoi: f64,
    /// Mean over steps of the power spent, in milliwatts.
    pub power_mw: f64,
    /// Steps in outage.
    pub outages: u32,
}

/// A sample mean with the half-width of its 95% confidence interval (Student's t).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub mean: f64,
    pub ci95: f64,
}

impl Estimate {
    pub fn from_samples(samples: impl IntoIterator<Item = f64>) -> Self {
        let samples: Vec<f64> = samples.into_iter().collect();
        let n = samples.len();
        if n == 0 {
            return Self {
                mean: f64::NAN,
                ci95: f64::NAN,
            };
        }
        let mean = samples.iter().sum::<f64>() / n as f64;
        if n == 1 {
            return Self { mean, ci95: 0.0 };
        }
        let var = samples.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        Self {
            mean,
            ci95: student_t_975(n - 1) * (var / n as f64).sqrt(),
        }
    }
}

impl std::fmt::Display for Estimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let precision = f.precision().unwrap_or(3);
        write!(f, "{:.p$} ± {:.p$}", self.mean, self.ci95, p = precision)
    }
}

/// The 97.5% quantile of Student's t with `dof` degrees of freedom.
fn student_t_975(dof: usize) -> f64 {
    const TABLE: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042,
    ];
    match dof {
        0 => f64::NAN,
        1..=30 => TABLE[dof - 1],
        // Beyond 30 the normal approximation with a 1/dof correction is within 0.1%.
        _ => 1.959_964 + 2.4 / dof as f64,
    }
}

/// How far `ret` lies from `reference`, in percent of the reference's size: returns are costs
/// (negative), so a return 3% below the planner's reads -3.0. Every table that sets a method
/// beside the planner reference uses this one reading.
pub fn percent_from(ret: f64, reference: f64) -> f64 {
    100.0 * (ret - reference) / reference.abs()
}

/// How a table marks a return above the planner's, beside its [`percent_from`]: there the planner
/// is a search, not the optimum (docs/MODEL.md section 9), and the table's note says by how much.
pub const ABOVE_PLANNER: &str = "*";

/// How a table marks a learned row whose return is below the greedy heuristic's: a policy that
/// has not learnt the task from its shots, whatever its gap to the planner (the table's note
/// names the rows and the heuristic's return).
pub const BELOW_GREEDY: &str = "!";

/// A return's gap to the planner as every table writes it: `-3.0%`, or `+1.0%*` where it is
/// above the planner ([`ABOVE_PLANNER`]).
pub fn gap_to_planner(ret: f64, planner: f64) -> String {
    let mark = if ret > planner { ABOVE_PLANNER } else { "" };
    format!("{:+.1}%{mark}", percent_from(ret, planner))
}

/// A policy's Monte-Carlo figures over a set of episodes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PolicyMetrics {
    pub episodes: usize,
    pub ret: Estimate,
    pub aoi: Estimate,
    pub power_mw: Estimate,
    pub outages: Estimate,
}

impl PolicyMetrics {
    /// The four estimates as CSV cells, each mean beside its interval, as every log writes them:
    /// `return,return_ci95,aoi,aoi_ci95,power_mw,power_mw_ci95,outages,outages_ci95`.
    pub fn csv(&self) -> String {
        let cells = [self.ret, self.aoi, self.power_mw, self.outages];
        let cells = cells.map(|e| format!("{},{}", e.mean, e.ci95));
        cells.join(",")
    }

    /// The estimates from the eight cells [`PolicyMetrics::csv`] writes, with `episodes`.
    pub fn parse_csv(cells: &[&str], episodes: usize) -> Option<Self> {
        let num = |i: usize| cells.get(i)?.parse::<f64>().ok();
        let estimate = |i: usize| {
            Some(Estimate {
                mean: num(i)?,
                ci95: num(i + 1)?,
            })
        };
        Some(Self {
            episodes,
            ret: estimate(0)?,
            aoi: estimate(2)?,
            power_mw: estimate(4)?,
            outages: estimate(6)?,
        })
    }

    pub fn from_episodes(episodes: &[EpisodeMetrics]) -> Self {
        Self {
            episodes: episodes.len(),
            ret: Estimate::from_samples(episodes.iter().map(|e| e.ret)),
            aoi: Estimate::from_samples(episodes.iter().map(|e| e.aoi)),
            power_mw: Estimate::from_samples(episodes.iter().map(|e| e.power_mw)),
            outages: Estimate::from_samples(episodes.iter().map(|e| e.outages as f64)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn estimate_matches_hand_computation() {
        // mean 2, sample variance 1, n = 3: half-width t(2) * sqrt(1/3) = 4.303 * 0.57735.
        let e = Estimate::from_samples([1.0, 2.0, 3.0]);
        assert!((e.mean - 2.0).abs() < 1e-12);
        assert!((e.ci95 - 4.303 * (1.0f64 / 3.0).sqrt()).abs() < 1e-9);
    }

    #[test]
    fn single_sample_has_zero_width() {
        let e = Estimate::from_samples([5.0]);
        assert_eq!((e.mean, e.ci95), (5.0, 0.0));
    }
}
