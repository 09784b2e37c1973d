//! `--profile FILE.json`: per-node timings over `--repeat` runs. Timings live here and in the run
//! summary, never in graph outputs, so outputs stay comparable and snapshot-testable.

use std::collections::BTreeMap;
use std::path::Path;

use ocellus_engine::RunReport;
use ocellus_engine::exec::NodeStatus;
use serde::Serialize;

/// Timings of one node.
#[derive(Debug, Serialize)]
pub struct NodeProfile {
    /// Operator id.
    pub op: String,
    /// Median over the runs, milliseconds.
    pub median_ms: f64,
    /// Fastest run, milliseconds.
    pub min_ms: f64,
    /// Slowest run, milliseconds.
    pub max_ms: f64,
}

/// The documented profile JSON:
/// `{"nodes": {"NODE": {"op", "median_ms", "min_ms", "max_ms"}}, "total_median_ms", "peak_bytes"}`.
#[derive(Debug, Serialize)]
pub struct Profile {
    /// Per computed node.
    pub nodes: BTreeMap<String, NodeProfile>,
    /// Median wall time of a whole run, milliseconds.
    pub total_median_ms: f64,
    /// Largest live output bytes in any run.
    pub peak_bytes: u64,
}

impl Profile {
    /// Aggregates the reports of repeated runs.
    pub fn from_reports(reports: &[RunReport]) -> Profile {
        let mut samples: BTreeMap<String, (String, Vec<f64>)> = BTreeMap::new();
        for report in reports {
            for node in report
                .nodes
                .iter()
                .filter(|n| n.status == NodeStatus::Computed)
            {
                samples
                    .entry(node.name.clone())
                    .or_insert_with(|| (node.op.clone(), Vec::new()))
                    .1
                    .push(node.elapsed.as_secs_f64() * 1e3);
            }
        }
        let nodes = samples
            .into_iter()
            .map(|(name, (op, mut ms))| {
                ms.sort_by(f64::total_cmp);
                let profile = NodeProfile {
                    op,
                    median_ms: median(&ms),
                    min_ms: ms.first().copied().unwrap_or(0.0),
                    max_ms: ms.last().copied().unwrap_or(0.0),
                };
                (name, profile)
            })
            .collect();
        let mut totals: Vec<f64> = reports
            .iter()
            .map(|r| r.elapsed.as_secs_f64() * 1e3)
            .collect();
        totals.sort_by(f64::total_cmp);
        Profile {
            nodes,
            total_median_ms: median(&totals),
            peak_bytes: reports
                .iter()
                .map(|r| r.peak_bytes as u64)
                .max()
                .unwrap_or(0),
        }
    }

    /// Writes the JSON atomically.
    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        let text = serde_json::to_string_pretty(self).map_err(std::io::Error::other)?;
        ocellus_engine::image_io::write_atomic(path, format!("{text}\n").as_bytes())
    }
}

/// Median of sorted samples (mean of the middle two for an even count); 0 when empty.
pub(crate) fn median(sorted: &[f64]) -> f64 {
    match sorted.len() {
        0 => 0.0,
        n if n % 2 == 1 => sorted[n / 2],
        n => (sorted[n / 2 - 1] + sorted[n / 2]) / 2.0,
    }
}

#[cfg(test)]
mod tests {
    use super::median;

    #[test]
    fn medians() {
        assert_eq!(median(&[]), 0.0);
        assert_eq!(median(&[3.0]), 3.0);
        assert_eq!(median(&[1.0, 2.0, 10.0]), 2.0);
        assert_eq!(median(&[1.0, 2.0, 4.0, 10.0]), 3.0);
    }
}
