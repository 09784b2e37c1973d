//! `io.read_correspondences`: read point correspondences from a text file.
//!
//! Two line formats are accepted (the first data line decides; all lines must then agree):
//! - 4 columns `x1 y1 x2 y2`: left point, right point, pixels;
//! - 7 columns `x1 y1 w1 x2 y2 w2 flag`: homogeneous left and right points (divided by `w`,
//!   which must be nonzero) and an integer flag per correspondence (e.g. 1 = hand-checked
//!   correct), the layout of the CMP "EVD"/"kusvod2" correspondence sets.
//!
//! Values are separated by spaces, tabs or commas; `#` starts a comment (to the end of the line);
//! blank lines are skipped.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_engine::value::Matrix;
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

ocellus_engine::params! {
    /// Parameters of [`ReadCorrespondences`].
    pub struct ReadCorrespondencesParams {
        /// The text file; relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
    }
}

/// Parsed correspondences.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrespondenceFile {
    /// Left points, pixels.
    pub left: Vec<[f64; 2]>,
    /// Right points, pixels.
    pub right: Vec<[f64; 2]>,
    /// Per-correspondence flags (7-column format only).
    pub flags: Option<Vec<i64>>,
}

/// Parses correspondence text (see the module documentation). Errors name the 1-based line.
pub fn parse_correspondences(text: &str) -> Result<CorrespondenceFile, String> {
    let mut out = CorrespondenceFile {
        left: Vec::new(),
        right: Vec::new(),
        flags: None,
    };
    let mut columns = None;
    for (index, raw) in text.lines().enumerate() {
        let line_no = index + 1;
        let line = raw.split('#').next().unwrap_or("");
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if fields.is_empty() {
            continue;
        }
        let expected = *columns.get_or_insert(fields.len());
        if expected != 4 && expected != 7 {
            return Err(format!(
                "line {line_no}: {} values; expected 4 (x1 y1 x2 y2) or 7 (x1 y1 w1 x2 y2 w2 flag)",
                fields.len()
            ));
        }
        if fields.len() != expected {
            return Err(format!(
                "line {line_no}: {} values, but earlier lines have {expected}",
                fields.len()
            ));
        }
        let mut values = [0.0f64; 7];
        for (k, f) in fields.iter().enumerate() {
            let v: f64 = f
                .parse()
                .map_err(|_| format!("line {line_no}: value {} `{f}` is not a number", k + 1))?;
            if !v.is_finite() {
                return Err(format!(
                    "line {line_no}: value {} `{f}` is not finite",
                    k + 1
                ));
            }
            values[k] = v;
        }
        if expected == 4 {
            out.left.push([values[0], values[1]]);
            out.right.push([values[2], values[3]]);
        } else {
            let (w1, w2) = (values[2], values[5]);
            if w1 == 0.0 || w2 == 0.0 {
                return Err(format!(
                    "line {line_no}: homogeneous coordinate w is 0 (a point at infinity)"
                ));
            }
            let flag = values[6];
            if flag.fract() != 0.0 {
                return Err(format!(
                    "line {line_no}: flag `{}` is not an integer",
                    fields[6]
                ));
            }
            out.left.push([values[0] / w1, values[1] / w1]);
            out.right.push([values[3] / w2, values[4] / w2]);
            out.flags.get_or_insert_with(Vec::new).push(flag as i64);
        }
    }
    Ok(out)
}

/// Reads and parses a correspondence file.
pub fn read_correspondences(path: &Path) -> Result<CorrespondenceFile, OpError> {
    let text = ocellus_engine::limits::read_text(path).map_err(|e| OpError::io(path, e))?;
    parse_correspondences(&text).map_err(|e| OpError::failed(format!("{}: {e}", path.display())))
}

/// `io.read_correspondences`. See [`parse_correspondences`].
pub struct ReadCorrespondences {
    params: ReadCorrespondencesParams,
}

impl Op for ReadCorrespondences {
    type Params = ReadCorrespondencesParams;
    const ID: &'static str = "io.read_correspondences";
    const SUMMARY: &'static str =
        "Read point correspondences (x1 y1 x2 y2 per line) from a text file.";
    const DOC: &'static str = r#"
Reads one correspondence per line in one of two formats, decided by the first data line:
`x1 y1 x2 y2` (left point, right point, pixels), or the 7-column `x1 y1 w1 x2 y2 w2 flag`
(homogeneous points, divided by w, plus an integer flag such as 1 = verified correct; the format
of the CMP EVD / kusvod2 correspondence sets). Values may be separated by spaces, tabs or
commas; `#` starts a comment; blank lines are skipped. Malformed lines (wrong value count,
non-numbers, NaN/Inf, w = 0, fractional flags) are errors naming the line number. An empty file
gives empty point lists.

Outputs `points_left` and `points_right` (Points2D, aligned) and `flags` (an N×1 Matrix of the
flags; 0×1 for the 4-column format).

Example:
    "matches": (op: "io.read_correspondences", params: (path: "data/ransac_homography_pts.txt")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("points_left", PortType::Points2D, "Left points, pixels."),
            PortSpec::new(
                "points_right",
                PortType::Points2D,
                "Right points, pixels, aligned with points_left.",
            ),
            PortSpec::new(
                "flags",
                PortType::Matrix,
                "N×1 flags of the 7-column format; 0×1 when the file has none.",
            ),
        ]
    }

    fn new(params: ReadCorrespondencesParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadCorrespondences { params })
    }
}

impl Operator for ReadCorrespondences {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let file = read_correspondences(&self.params.path)?;
        let flags: Vec<f64> = file
            .flags
            .unwrap_or_default()
            .into_iter()
            .map(|f| f as f64)
            .collect();
        Ok(Outputs::new()
            .with("points_left", Value::Points2D(Arc::new(file.left)))
            .with("points_right", Value::Points2D(Arc::new(file.right)))
            .with(
                "flags",
                Value::Matrix(Arc::new(Matrix {
                    rows: flags.len(),
                    cols: 1,
                    data: flags,
                })),
            ))
    }

    /// The file's contents decide the result, so they are part of the cache key.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let bytes = ocellus_engine::limits::read_file(&self.params.path)
            .map_err(|e| OpError::io(&self.params.path, e))?;
        Ok(ocellus_engine::cache::content_hash(&bytes).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_four_columns_with_comments_and_blank_lines() {
        let text = "# left right\n1 2 3 4\n\n  5.5\t6, 7 8 # trailing\n";
        let f = parse_correspondences(text).unwrap();
        assert_eq!(f.left, vec![[1.0, 2.0], [5.5, 6.0]]);
        assert_eq!(f.right, vec![[3.0, 4.0], [7.0, 8.0]]);
        assert_eq!(f.flags, None);
    }

    #[test]
    fn parses_seven_columns_dividing_by_w() {
        let text = "175.5 520 1 193 483.5 1 0\n4 6 2 9 3 3 1\n";
        let f = parse_correspondences(text).unwrap();
        assert_eq!(f.left, vec![[175.5, 520.0], [2.0, 3.0]]);
        assert_eq!(f.right, vec![[193.0, 483.5], [3.0, 1.0]]);
        assert_eq!(f.flags, Some(vec![0, 1]));
    }

    #[test]
    fn errors_name_the_line() {
        for (text, needle) in [
            ("1 2 3 4\n1 2 3\n", "line 2"),
            ("1 2 3\n", "line 1"),
            ("1 2 3 4\n\n1 2 x 4\n", "line 3"),
            ("1 2 3 NaN\n", "line 1"),
            ("1 2 0 4 5 1 1\n", "line 1"),
            ("1 2 1 4 5 1 0.5\n", "line 1"),
        ] {
            let e = parse_correspondences(text).unwrap_err();
            assert!(e.contains(needle), "{text:?}: {e}");
        }
        assert_eq!(parse_correspondences("# nothing\n").unwrap().left.len(), 0);
    }

    #[test]
    fn operator_reads_a_file() {
        let dir = std::env::temp_dir().join(format!("ocellus-corr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("c.txt");
        std::fs::write(&path, "1 2 3 4\n").unwrap();
        let op =
            ReadCorrespondences::new(ReadCorrespondencesParams { path: path.clone() }).unwrap();
        let ctx = RunContext {
            node: "m".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&[], &[])).unwrap();
        assert_eq!(
            out.take("points_left"),
            Some(Value::Points2D(Arc::new(vec![[1.0, 2.0]])))
        );
        assert!(op.fingerprint().is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(op.run(&ctx, &Inputs::new(&[], &[])).is_err());
        assert!(ReadCorrespondences::new(ReadCorrespondencesParams::default()).is_err());
    }
}
