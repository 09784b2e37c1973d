//! `sfm.tracks`: feature tracks from pairwise verified matches by union-find (Moulon & Monasse,
//! "Unordered feature tracking made fast and easy", CVMP 2012).
//!
//! Every keypoint of every image is a node; every verified match joins two nodes. A connected
//! component is a track — the observations of one scene point. A component that holds two
//! different keypoints of the same image is inconsistent (a wrong match somewhere along it);
//! with `conflicts: "drop_image"` (the default) the observations of the images it sees more
//! than once are removed and the rest kept, with `"drop_track"` the whole track goes. Tracks
//! shorter than `min_length` are dropped. Tracks are ordered by their first observation
//! (image, then keypoint) and each track's observations by image, so the result does not
//! depend on the order of the pairs or on the thread count.

use std::sync::Arc;

use ocellus_engine::value::{Match, Metrics, TrackElement, Tracks, Value};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, param_enum, params,
};

use super::pairs::{keypoint_lists, read_pairs, required_list};

/// Union-find with path halving and union by size; the smaller root index wins ties.
#[derive(Debug, Clone)]
pub struct UnionFind {
    parent: Vec<u32>,
    size: Vec<u32>,
}

impl UnionFind {
    /// `n` singletons.
    pub fn new(n: usize) -> UnionFind {
        UnionFind {
            parent: (0..n as u32).collect(),
            size: vec![1; n],
        }
    }

    /// The root of `x`'s set.
    pub fn find(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = self.parent[x as usize];
        }
        x
    }

    /// Joins the sets of `a` and `b`.
    pub fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra == rb {
            return;
        }
        let (big, small) = match self.size[ra as usize].cmp(&self.size[rb as usize]) {
            std::cmp::Ordering::Greater => (ra, rb),
            std::cmp::Ordering::Less => (rb, ra),
            std::cmp::Ordering::Equal => (ra.min(rb), ra.max(rb)),
        };
        self.parent[small as usize] = big;
        self.size[big as usize] += self.size[small as usize];
    }
}

param_enum! {
    /// What happens to a track that sees one image twice.
    pub enum ConflictPolicy {
        /// Remove the observations of the images it sees more than once.
        DropImage = "drop_image",
        /// Remove the whole track.
        DropTrack = "drop_track",
    }
}

/// Counts of [`build_tracks`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TrackStats {
    /// Tracks kept.
    pub tracks: usize,
    /// Observations in kept tracks.
    pub observations: usize,
    /// Components that saw an image twice.
    pub conflicting: usize,
    /// Tracks dropped as shorter than the minimum (after conflict removal).
    pub short: usize,
}

/// Tracks from the verified `matches` of image pairs `(i, j)` (query in `i`, train in `j`)
/// over images with `keypoint_counts[i]` keypoints. Matches naming a keypoint out of range are
/// an error.
pub fn build_tracks(
    keypoint_counts: &[usize],
    pairs: &[(usize, usize)],
    matches: &[&[Match]],
    min_length: usize,
    policy: ConflictPolicy,
) -> Result<(Tracks, TrackStats), String> {
    let mut offset = Vec::with_capacity(keypoint_counts.len() + 1);
    let mut total = 0usize;
    for &c in keypoint_counts {
        offset.push(total);
        total += c;
    }
    offset.push(total);
    if total > u32::MAX as usize {
        return Err(format!(
            "{total} keypoints in all; at most {} supported",
            u32::MAX
        ));
    }
    let mut uf = UnionFind::new(total);
    for (&(i, j), ms) in pairs.iter().zip(matches) {
        for m in *ms {
            let (q, t) = (m.query as usize, m.train as usize);
            if q >= keypoint_counts[i] || t >= keypoint_counts[j] {
                return Err(format!(
                    "pair ({i}, {j}): match ({q}, {t}) is out of range ({} and {} keypoints)",
                    keypoint_counts[i], keypoint_counts[j]
                ));
            }
            uf.union((offset[i] + q) as u32, (offset[j] + t) as u32);
        }
    }
    // Group nodes by root, in node order (image, then keypoint).
    let mut members: Vec<Vec<u32>> = Vec::new();
    let mut slot = vec![u32::MAX; total];
    let mut size_of_root = vec![0u32; total];
    for x in 0..total as u32 {
        let r = uf.find(x);
        size_of_root[r as usize] += 1;
    }
    for x in 0..total as u32 {
        let r = uf.find(x) as usize;
        if size_of_root[r] < 2 {
            continue;
        }
        if slot[r] == u32::MAX {
            slot[r] = members.len() as u32;
            members.push(Vec::new());
        }
        members[slot[r] as usize].push(x);
    }
    let image_of = |x: u32| -> usize { offset.partition_point(|&o| o <= x as usize) - 1 };
    let mut stats = TrackStats::default();
    let mut tracks = Vec::new();
    for nodes in members {
        let mut elements: Vec<TrackElement> = nodes
            .iter()
            .map(|&x| {
                let im = image_of(x);
                TrackElement {
                    image: im as u32,
                    keypoint: (x as usize - offset[im]) as u32,
                }
            })
            .collect();
        // Nodes are in increasing order, so elements are sorted by image, then keypoint.
        let duplicated: Vec<u32> = elements
            .windows(2)
            .filter(|w| w[0].image == w[1].image)
            .map(|w| w[0].image)
            .collect();
        if !duplicated.is_empty() {
            stats.conflicting += 1;
            match policy {
                ConflictPolicy::DropTrack => continue,
                ConflictPolicy::DropImage => elements.retain(|e| !duplicated.contains(&e.image)),
            }
        }
        if elements.len() < min_length.max(2) {
            stats.short += 1;
            continue;
        }
        stats.observations += elements.len();
        tracks.push(elements);
    }
    stats.tracks = tracks.len();
    Ok((Tracks { tracks }, stats))
}

params! {
    /// Parameters of `sfm.tracks`.
    pub struct TracksParams {
        /// Shortest track kept, observations (at least 2).
        min_length: u32 = 2 => [min = 2],
        /// A track that sees an image twice: "drop_image" removes that image's observations,
        /// "drop_track" the whole track.
        conflicts: ConflictPolicy = ConflictPolicy::DropImage,
    }
}

/// `sfm.tracks`. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct TracksOp {
    min_length: usize,
    policy: ConflictPolicy,
}

impl Op for TracksOp {
    type Params = TracksParams;
    const ID: &'static str = "sfm.tracks";
    const SUMMARY: &'static str = "Feature tracks from verified pairwise matches (union-find).";
    const DOC: &'static str = r#"
Joins the verified matches of `sfm.match_pairs` into tracks by union-find (Moulon & Monasse,
CVMP 2012): the connected components of the graph whose nodes are keypoints and whose edges
are matches. A component holding two keypoints of one image is inconsistent: `conflicts:
"drop_image"` removes the observations of the images it sees twice, `"drop_track"` removes
it. Tracks shorter than `min_length` are dropped. Tracks are ordered by their first
observation and observations by image.

Outputs: `tracks` and `report` (tracks, observations, mean_length, conflicting, short).

Example:
    "tracks": (op: "sfm.tracks", inputs: { "keypoints": "features.keypoints",
               "matches": "pairs.matches", "pairs": "pairs.pairs" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints.list_of(),
                "Keypoints of every image (for the counts).",
            ),
            PortSpec::new(
                "matches",
                PortType::Matches.list_of(),
                "Verified matches per pair (sfm.match_pairs).",
            ),
            PortSpec::new(
                "pairs",
                PortType::Matrix,
                "The pairs the matches belong to (sfm.match_pairs).",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("tracks", PortType::Tracks, "The tracks."),
            PortSpec::new(
                "report",
                PortType::Metrics,
                "tracks, observations, mean_length, conflicting, short.",
            ),
        ]
    }

    fn new(p: TracksParams) -> Result<Self, String> {
        Ok(TracksOp {
            min_length: p.min_length as usize,
            policy: p.conflicts,
        })
    }
}

impl Operator for TracksOp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let keypoints = keypoint_lists(inputs, "keypoints")?;
        let matches: Vec<&[Match]> =
            required_list(inputs, "matches", PortType::Matches, |v| match v {
                Value::Matches(m) => Some(m.as_slice()),
                _ => None,
            })?;
        let pairs = match inputs.require("pairs")? {
            Value::Matrix(m) => {
                read_pairs(m, keypoints.len()).map_err(|e| OpError::input("pairs", e))?
            }
            other => {
                return Err(OpError::input(
                    "pairs",
                    format!("expected Matrix, got {}", other.port_type()),
                ));
            }
        };
        if pairs.len() != matches.len() {
            return Err(OpError::input(
                "matches",
                format!(
                    "holds {} match sets but pairs has {} rows",
                    matches.len(),
                    pairs.len()
                ),
            ));
        }
        let counts: Vec<usize> = keypoints.iter().map(|k| k.len()).collect();
        let ij: Vec<(usize, usize)> = pairs.iter().map(|p| (p.i, p.j)).collect();
        let (tracks, stats) = build_tracks(&counts, &ij, &matches, self.min_length, self.policy)
            .map_err(|e| OpError::input("matches", e))?;
        let mut report = Metrics::new();
        report.insert("tracks".into(), stats.tracks as f64);
        report.insert("observations".into(), stats.observations as f64);
        report.insert(
            "mean_length".into(),
            if stats.tracks == 0 {
                0.0
            } else {
                stats.observations as f64 / stats.tracks as f64
            },
        );
        report.insert("conflicting".into(), stats.conflicting as f64);
        report.insert("short".into(), stats.short as f64);
        Ok(Outputs::new()
            .with("tracks", Value::Tracks(Arc::new(tracks)))
            .with("report", Value::metrics(report)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(query: u32, train: u32) -> Match {
        Match {
            query,
            train,
            distance: 0.0,
        }
    }

    fn el(image: u32, keypoint: u32) -> TrackElement {
        TrackElement { image, keypoint }
    }

    #[test]
    fn chains_of_matches_become_one_track_in_image_order() {
        // 0:1 — 1:2 — 2:0, and a separate 0:0 — 2:3.
        let counts = [2, 3, 4];
        let pairs = [(1, 2), (0, 1), (0, 2)];
        let ms: [&[Match]; 3] = [&[m(2, 0)], &[m(1, 2)], &[m(0, 3)]];
        let (t, s) = build_tracks(&counts, &pairs, &ms, 2, ConflictPolicy::DropImage).unwrap();
        assert_eq!(
            t.tracks,
            vec![vec![el(0, 0), el(2, 3)], vec![el(0, 1), el(1, 2), el(2, 0)]]
        );
        assert_eq!((s.tracks, s.observations, s.conflicting), (2, 5, 0));
        // The pair order does not matter.
        let pairs2 = [(0, 2), (0, 1), (1, 2)];
        let ms2: [&[Match]; 3] = [&[m(0, 3)], &[m(1, 2)], &[m(2, 0)]];
        let (t2, _) = build_tracks(&counts, &pairs2, &ms2, 2, ConflictPolicy::DropImage).unwrap();
        assert_eq!(t, t2);
    }

    #[test]
    fn conflicts_drop_the_image_or_the_track() {
        // 0:0 — 1:0 — 2:0 — 1:1: image 1 twice.
        let counts = [1, 2, 1];
        let pairs = [(0, 1), (1, 2), (1, 2)];
        let ms: [&[Match]; 3] = [&[m(0, 0)], &[m(0, 0)], &[m(1, 0)]];
        let (t, s) = build_tracks(&counts, &pairs, &ms, 2, ConflictPolicy::DropImage).unwrap();
        assert_eq!(t.tracks, vec![vec![el(0, 0), el(2, 0)]]);
        assert_eq!(s.conflicting, 1);
        let (t, _) = build_tracks(&counts, &pairs, &ms, 2, ConflictPolicy::DropTrack).unwrap();
        assert!(t.tracks.is_empty());
        // Minimum length 3 drops the two-view track that remains.
        let (t, s) = build_tracks(&counts, &pairs, &ms, 3, ConflictPolicy::DropImage).unwrap();
        assert!(t.tracks.is_empty());
        assert_eq!(s.short, 1);
    }

    #[test]
    fn out_of_range_matches_are_an_error() {
        let ms: [&[Match]; 1] = [&[m(5, 0)]];
        let e = build_tracks(&[2, 2], &[(0, 1)], &ms, 2, ConflictPolicy::DropImage).unwrap_err();
        assert!(e.contains("out of range"), "{e}");
    }

    #[test]
    fn union_find_joins_transitively() {
        let mut uf = UnionFind::new(6);
        uf.union(0, 1);
        uf.union(2, 3);
        uf.union(1, 3);
        assert_eq!(uf.find(0), uf.find(2));
        assert_ne!(uf.find(0), uf.find(4));
        uf.union(4, 5);
        assert_eq!(uf.find(4), uf.find(5));
        assert_ne!(uf.find(5), uf.find(3));
    }
}
