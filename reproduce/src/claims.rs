//! Deciding the claims of docs/MODEL.md section 6 from measured curves: the statistics of a curve
//! (final return, the epoch it settles, whether it converged), the rules that turn comparisons
//! into "yes / partly / no", and the markdown table every `summary.md` shows.
//!
//! The rules, the same for every claim:
//! - "A beats B" (higher is better): **yes** when A's 95% interval lies wholly above B's,
//!   **partly** when only A's mean is higher, **no** otherwise.
//! - "A is about x" (within a range): **yes** when A's 95% interval lies wholly in it, **partly**
//!   when only its mean does, **no** otherwise.
//! - A claim over several cases (every shot count, every seed): **yes** when every case holds,
//!   **no** when none does, **partly** in between.
//! - A claim the run was too short to test (fewer epochs than the claim's) is **untested**.

use std::fmt;
use std::fmt::Write as _;

use uavmeta_proto::stats::Estimate;

/// Epochs averaged into a curve's final return, so one noisy evaluation does not define it.
pub const FINAL_EPOCHS: usize = 10;
/// Width of the trailing moving average a curve is smoothed with before the 5% test.
pub const SMOOTH_EPOCHS: usize = 5;
/// A curve that settles only in this last share of its epochs cannot be told from noise
/// settling: it has not converged within the run.
pub const LATE_SHARE: f64 = 0.1;

/// How far a claim holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Yes,
    Partly,
    No,
    Untested,
}

impl fmt::Display for Verdict {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Verdict::Yes => "yes",
            Verdict::Partly => "partly",
            Verdict::No => "no",
            Verdict::Untested => "untested",
        })
    }
}

impl Verdict {
    /// Every case holds: yes; none: no; some, or partly: partly. Untested cases are left out,
    /// but cannot make a "yes": with every tested case holding and some untested, the whole is
    /// untested.
    pub fn all_of(cases: impl IntoIterator<Item = Verdict>) -> Verdict {
        let cases: Vec<Verdict> = cases.into_iter().collect();
        let tested: Vec<Verdict> = cases
            .iter()
            .copied()
            .filter(|v| *v != Verdict::Untested)
            .collect();
        if tested.len() < cases.len() && tested.iter().all(|v| *v == Verdict::Yes) {
            Verdict::Untested
        } else if tested.iter().all(|v| *v == Verdict::Yes) {
            Verdict::Yes
        } else if tested.iter().all(|v| *v == Verdict::No) {
            Verdict::No
        } else {
            Verdict::Partly
        }
    }

    /// `held` of `cases` cases hold.
    pub fn share(held: usize, cases: usize) -> Verdict {
        match (held, cases) {
            (_, 0) => Verdict::Untested,
            (0, _) => Verdict::No,
            (h, n) if h == n => Verdict::Yes,
            _ => Verdict::Partly,
        }
    }

    /// `a` beats `b`, higher being better.
    pub fn beats(a: Estimate, b: Estimate) -> Verdict {
        if a.mean - a.ci95 > b.mean + b.ci95 {
            Verdict::Yes
        } else if a.mean > b.mean {
            Verdict::Partly
        } else {
            Verdict::No
        }
    }

    /// `value` lies in `lo..=hi`: **yes** when its whole 95% interval does, **partly** when only
    /// its mean does, **no** otherwise.
    pub fn within(value: Estimate, lo: f64, hi: f64) -> Verdict {
        if value.mean - value.ci95 >= lo && value.mean + value.ci95 <= hi {
            Verdict::Yes
        } else if (lo..=hi).contains(&value.mean) {
            Verdict::Partly
        } else {
            Verdict::No
        }
    }
}

/// One row of a claims table.
#[derive(Debug, Clone, PartialEq)]
pub struct Claim {
    /// The figure it belongs to, e.g. "5".
    pub figure: &'static str,
    /// The paper's statement (docs/MODEL.md section 6).
    pub paper: &'static str,
    /// Our figure, mean ± 95% CI over seeds.
    pub measured: String,
    pub verdict: Verdict,
    /// Why we think it does not hold, from the measured figures; empty when it holds.
    pub why: String,
}

impl Claim {
    pub fn new(
        figure: &'static str,
        paper: &'static str,
        measured: String,
        verdict: Verdict,
        why: impl FnOnce() -> String,
    ) -> Self {
        let why = match verdict {
            Verdict::Yes => String::new(),
            Verdict::Untested => {
                "the run is shorter than the claim (`--quick` or a smaller config)".into()
            }
            Verdict::Partly | Verdict::No => why(),
        };
        Self {
            figure,
            paper,
            measured,
            verdict,
            why,
        }
    }
}

/// The markdown table of `claims`.
pub fn table(claims: &[Claim]) -> String {
    let mut s = String::from(
        "| fig. | the paper says | we measured (mean ± 95% CI over seeds) | holds? | why we think it does not |\n\
         | --- | --- | --- | --- | --- |\n",
    );
    for c in claims {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} |",
            c.figure,
            c.paper,
            c.measured.replace('|', "/"),
            c.verdict,
            c.why.replace('|', "/")
        );
    }
    s
}

/// Mean of the last [`FINAL_EPOCHS`] returns.
pub fn final_return(returns: &[f64]) -> f64 {
    let tail = &returns[returns.len().saturating_sub(FINAL_EPOCHS)..];
    tail.iter().sum::<f64>() / tail.len() as f64
}

/// The curve averaged over a trailing window of [`SMOOTH_EPOCHS`] epochs (shorter at the start).
pub fn smoothed(returns: &[f64]) -> Vec<f64> {
    (0..returns.len())
        .map(|i| {
            let window = &returns[(i + 1).saturating_sub(SMOOTH_EPOCHS)..=i];
            window.iter().sum::<f64>() / window.len() as f64
        })
        .collect()
}

/// The first epoch (from 1) from which the smoothed curve stays within 5% of the final return.
pub fn settle_epoch(returns: &[f64]) -> usize {
    let last = final_return(returns);
    let outside = |r: &f64| (r - last).abs() > 0.05 * last.abs();
    smoothed(returns)
        .iter()
        .rposition(outside)
        .map_or(1, |i| i + 2)
        .min(returns.len())
}

/// The epoch a curve converged at: it settled (see [`settle_epoch`]) before the last
/// [`LATE_SHARE`] of its epochs, at a final return above `floor` (the uniform random policy's:
/// settling below it is failing to learn, not converging). `None` when it did not.
pub fn converged_at(returns: &[f64], floor: f64) -> Option<usize> {
    let epoch = settle_epoch(returns);
    let late = ((1.0 - LATE_SHARE) * returns.len() as f64).ceil() as usize;
    (epoch <= late.max(1) && final_return(returns) > floor).then_some(epoch)
}

/// The mean over a run of |return(e) - return(e-1)|: how much a curve swings between epochs.
pub fn mean_swing(returns: &[f64]) -> f64 {
    if returns.len() < 2 {
        return 0.0;
    }
    returns.windows(2).map(|w| (w[1] - w[0]).abs()).sum::<f64>() / (returns.len() - 1) as f64
}

/// The mean of `curve` over the epochs `epoch - FINAL_EPOCHS + 1 ..= epoch` (1-based), or over
/// the whole curve if shorter: the "return at epoch E" of the claims, smoothed like the final one.
pub fn return_at(curve: &[f64], epoch: usize) -> f64 {
    final_return(&curve[..epoch.min(curve.len())])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn est(mean: f64, ci95: f64) -> Estimate {
        Estimate { mean, ci95 }
    }

    #[test]
    fn beating_needs_separate_intervals_for_yes() {
        assert_eq!(Verdict::beats(est(10.0, 1.0), est(5.0, 1.0)), Verdict::Yes);
        assert_eq!(
            Verdict::beats(est(10.0, 3.0), est(5.0, 3.0)),
            Verdict::Partly
        );
        assert_eq!(Verdict::beats(est(5.0, 0.0), est(5.0, 0.0)), Verdict::No);
        assert_eq!(Verdict::beats(est(-9.0, 0.1), est(-8.0, 0.1)), Verdict::No);
    }

    #[test]
    fn a_range_holds_an_estimate_by_its_interval() {
        let e = |mean, ci95| Estimate { mean, ci95 };
        assert_eq!(Verdict::within(e(20.0, 5.0), 10.0, 40.0), Verdict::Yes);
        assert_eq!(Verdict::within(e(12.0, 5.0), 10.0, 40.0), Verdict::Partly);
        assert_eq!(Verdict::within(e(8.0, 1.0), 10.0, 40.0), Verdict::No);
        assert_eq!(
            Verdict::within(e(0.2, 0.5), f64::NEG_INFINITY, 1.0),
            Verdict::Yes
        );
        assert_eq!(
            Verdict::within(e(0.8, 0.5), f64::NEG_INFINITY, 1.0),
            Verdict::Partly
        );
    }

    #[test]
    fn cases_combine_into_yes_partly_no() {
        use Verdict::*;
        assert_eq!(Verdict::all_of([Yes, Yes]), Yes);
        assert_eq!(Verdict::all_of([No, No, Untested]), No);
        assert_eq!(Verdict::all_of([Yes, No]), Partly);
        assert_eq!(Verdict::all_of([Partly, Yes]), Partly);
        assert_eq!(Verdict::all_of([Untested]), Untested);
        assert_eq!(Verdict::all_of([Yes, Untested]), Untested);
        assert_eq!(Verdict::all_of([No, Untested, Yes]), Partly);
        assert_eq!(Verdict::share(3, 3), Yes);
        assert_eq!(Verdict::share(0, 3), No);
        assert_eq!(Verdict::share(1, 3), Partly);
        assert_eq!(Verdict::share(0, 0), Untested);
    }

    #[test]
    fn a_curve_converges_where_its_smoothed_returns_stay_near_the_end() {
        // Rises for 20 epochs, then flat at -100 for 80: settles where the 5-epoch average
        // comes within 5% of -100.
        let mut curve: Vec<f64> = (0..20).map(|e| -1000.0 + 45.0 * e as f64).collect();
        curve.extend(std::iter::repeat_n(-100.0, 80));
        let epoch = settle_epoch(&curve);
        assert!((21..=25).contains(&epoch), "{epoch}");
        assert_eq!(converged_at(&curve, -5000.0), Some(epoch));
        // Flat below the random policy: settled, but not converged.
        assert_eq!(converged_at(&curve, 0.0), None);
        // Swinging between -100 and -300 until the end never settles before the last 10%.
        let swinging: Vec<f64> = (0..100)
            .map(|e| if e % 2 == 0 { -100.0 } else { -300.0 })
            .collect();
        assert_eq!(converged_at(&swinging, -5000.0), None);
        assert_eq!(mean_swing(&swinging), 200.0);
    }

    #[test]
    fn return_at_an_epoch_averages_the_epochs_up_to_it() {
        let curve: Vec<f64> = (1..=50).map(f64::from).collect();
        // Epochs 31..=40.
        assert_eq!(return_at(&curve, 40), 35.5);
        assert_eq!(return_at(&curve, 500), final_return(&curve));
        assert_eq!(smoothed(&[1.0, 3.0]), vec![1.0, 2.0]);
    }

    #[test]
    fn the_reason_is_kept_only_where_a_claim_fails() {
        let held = Claim::new("5", "x", "1".into(), Verdict::Yes, || "unused".into());
        assert!(held.why.is_empty());
        let failed = Claim::new("5", "x", "1".into(), Verdict::No, || "because".into());
        assert_eq!(failed.why, "because");
        let text = table(&[held, failed]);
        assert_eq!(text.lines().count(), 4);
        assert!(text.contains("| 5 | x | 1 | no | because |"));
    }
}
