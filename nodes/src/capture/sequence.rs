//! `capture.sequence`: an ordered list of frames read from a folder or a file-name pattern.

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use ocellus_engine::image_io::{DecodeLimits, ImageFormat, read_image};
use ocellus_engine::op::{
    FrameSource, Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext,
};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::Value;
use rayon::prelude::*;

params! {
    /// Parameters of `capture.sequence`.
    pub struct SequenceParams {
        /// A folder (every image file in it: png, jpg/jpeg, pgm/ppm/pnm/pam, tif/tiff, pfm, exr), or a
        /// pattern whose last component holds `*` (any run of characters) and `?` (one
        /// character), e.g. "frames/cam0_*.png". Relative paths resolve against the graph
        /// file's folder. Required.
        path: PathBuf = PathBuf::new(),
        /// Index of the first frame taken, in the sorted list (0-based). Default 0.
        start: u32 = 0,
        /// Take every `step`-th file from `start` (1 takes all). Default 1.
        step: u32 = 1 => [min = 1],
        /// Most frames taken; None (the default) takes all.
        limit: Option<u32> = None => [min = 1],
        /// Frame rate of the sequence: in a stream, frame k is stamped k / fps seconds.
        fps: f64 = 30.0 => [min = 0.001, max = 1000000.0, unit = "frames/s"],
    }
}

/// Frames from a folder or pattern (`capture.sequence`). See [`list_sequence`].
#[derive(Debug, Clone, PartialEq)]
pub struct Sequence {
    params: SequenceParams,
}

impl Op for Sequence {
    type Params = SequenceParams;
    const ID: &'static str = "capture.sequence";
    const SUMMARY: &'static str =
        "Reads an ordered sequence of image files from a folder or a pattern as a list.";
    const DOC: &'static str = r#"
Lists the files of a folder (image extensions only: png, jpg, jpeg, pgm, ppm, pnm, pam, tif,
tiff, pfm, exr, any case) or those matching a pattern in its last path component (`*` matches
any run of characters, `?` one character, case-sensitive; no other syntax, and wildcards in
earlier components are an error). Names starting with `.` are skipped unless the pattern
starts with `.`; only regular files (or links to them) count.

The files are sorted in natural order: runs of digits compare as numbers, so frame2 comes
before frame10 (ties broken by plain text order), then `start`, `step` and `limit` select
frames[start], frames[start + step], … Each is decoded as `io.read_image` does (format by
content, bit depth kept), in parallel, into `frames` in order; `count` is their number and
`names` their file names (without the folder), in the same order.
Frames may differ in size and format (an operator mapped over the list sees each on its own).

Errors: no file matches (naming the pattern and the folder), the selection is empty (start
beyond the matches), or a file cannot be read or decoded (naming it).

Caching: the fingerprint covers the selected file names and every selected file's content,
so the cache notices renamed, added, removed or rewritten frames.

A batch run holds every frame in memory at once. In a graph with a `stream` section the
node is a source: frames are decoded one at a time as the pipeline asks for them (frame k
stamped k / `fps` s), so memory does not grow with the sequence; `count` is known before the
first frame.

Example:
    "frames": (op: "capture.sequence", params: (path: "shots/img_*.png", step: 2, limit: 10)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "The decoded frames, in natural file-name order.",
            )
            .per_frame(),
            PortSpec::new("count", PortType::Integer, "Number of frames."),
            PortSpec::new(
                "names",
                PortType::Text.list_of(),
                "The file name (without its folder) of each frame, in the order of `frames`.",
            )
            .per_frame(),
        ]
    }

    fn new(params: SequenceParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        if params.step == 0 {
            return Err("`step` must be at least 1".into());
        }
        if !(params.fps.is_finite() && params.fps > 0.0) {
            return Err("`fps` must be a positive number".into());
        }
        if params.limit == Some(0) {
            return Err("`limit` must be at least 1".into());
        }
        if let Some(parent) = params.path.parent()
            && parent.to_string_lossy().contains(['*', '?'])
        {
            return Err(format!(
                "`path` {}: only the last component may hold `*` or `?`",
                params.path.display()
            ));
        }
        Ok(Sequence { params })
    }
}

impl Operator for Sequence {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let files = self.selected()?;
        let limits = DecodeLimits::default();
        let decoded: Vec<_> = files
            .par_iter()
            .map(|path| read_image(path, &limits))
            .collect();
        let mut frames = Vec::with_capacity(decoded.len());
        for (k, result) in decoded.into_iter().enumerate() {
            match result {
                Ok(image) => frames.push(Value::image(image)),
                Err(e) => return Err(OpError::failed(format!("frame {k}: {e}"))),
            }
        }
        let count = frames.len() as i64;
        let names = files
            .iter()
            .map(|path| Value::Text(file_name(path).into()))
            .collect();
        Ok(Outputs::new()
            .with("frames", Value::list(PortType::Image, frames))
            .with("count", Value::Integer(count))
            .with("names", Value::list(PortType::Text, names)))
    }

    /// The selected names and contents decide the result.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let files = self.selected()?;
        let mut all = Vec::with_capacity(files.len() * 64);
        for path in &files {
            let bytes =
                ocellus_engine::limits::read_file(path).map_err(|e| OpError::io(path, e))?;
            all.extend_from_slice(path.as_os_str().as_encoded_bytes());
            all.push(0);
            all.extend_from_slice(&ocellus_engine::cache::content_hash(&bytes));
        }
        Ok(ocellus_engine::cache::content_hash(&all).to_vec())
    }

    fn frame_source(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn FrameSource>, OpError>> {
        Some(self.selected().map(|files| {
            Box::new(SequenceSource {
                files,
                fps: self.params.fps,
            }) as Box<dyn FrameSource>
        }))
    }
}

/// `capture.sequence` as a stream source: one file decoded per frame.
struct SequenceSource {
    files: Vec<PathBuf>,
    fps: f64,
}

impl FrameSource for SequenceSource {
    fn frames(&self) -> usize {
        self.files.len()
    }

    fn timestamp_us(&self, index: usize) -> i64 {
        (index as f64 * 1e6 / self.fps).round() as i64
    }

    fn frame(&mut self, _ctx: &RunContext, index: usize) -> Result<Outputs, OpError> {
        let path = self
            .files
            .get(index)
            .ok_or_else(|| OpError::failed(format!("no frame {index}")))?;
        let image = read_image(path, &DecodeLimits::default())
            .map_err(|e| OpError::failed(format!("frame {index}: {e}")))?;
        Ok(Outputs::new()
            .with("frames", Value::image(image))
            .with("names", Value::Text(file_name(path).into())))
    }

    fn statics(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("count", Value::Integer(self.files.len() as i64)))
    }
}

/// The file name of `path` without its folder (empty when it has none).
fn file_name(path: &Path) -> String {
    path.file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
}

impl Sequence {
    /// The files selected by `start`, `step` and `limit`.
    fn selected(&self) -> Result<Vec<PathBuf>, OpError> {
        let p = &self.params;
        let all = list_sequence(&p.path)?;
        let total = all.len();
        let limit = p.limit.map_or(usize::MAX, |l| l as usize);
        let picked: Vec<PathBuf> = all
            .into_iter()
            .skip(p.start as usize)
            .step_by(p.step.max(1) as usize)
            .take(limit)
            .collect();
        if picked.is_empty() {
            return Err(OpError::failed(format!(
                "{}: start {} is beyond the {total} matching files",
                p.path.display(),
                p.start
            )));
        }
        Ok(picked)
    }
}

/// The files `path` names, in natural order: every image file of a folder, or the files of
/// the parent folder whose names match the last component (`*`, `?`). Errors when nothing
/// matches or the folder cannot be listed.
pub fn list_sequence(path: &Path) -> Result<Vec<PathBuf>, OpError> {
    let (folder, pattern) = if path.is_dir() {
        (path.to_path_buf(), None)
    } else {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .ok_or_else(|| {
                OpError::failed(format!(
                    "{}: neither a folder nor a file pattern",
                    path.display()
                ))
            })?;
        let folder = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        (folder, Some(name))
    };
    let entries = std::fs::read_dir(&folder).map_err(|e| OpError::io(&folder, e))?;
    let mut names = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| OpError::io(&folder, e))?;
        let Ok(name) = entry.file_name().into_string() else {
            continue;
        };
        let wanted = match &pattern {
            Some(p) => (!name.starts_with('.') || p.starts_with('.')) && wildcard_match(p, &name),
            None => !name.starts_with('.') && ImageFormat::from_path(Path::new(&name)).is_some(),
        };
        // `metadata` follows links: a link to a file counts, a folder does not.
        if wanted && std::fs::metadata(entry.path()).is_ok_and(|m| m.is_file()) {
            names.push(name);
        }
    }
    if names.is_empty() {
        let what = match &pattern {
            Some(p) => format!("no file matches `{p}`"),
            None => {
                "no image file (png, jpg, jpeg, pgm, ppm, pnm, pam, tif, tiff, pfm, exr)".into()
            }
        };
        return Err(OpError::failed(format!(
            "{what} in folder {}",
            folder.display()
        )));
    }
    names.sort_by(|a, b| natural_cmp(a, b));
    Ok(names.into_iter().map(|n| folder.join(n)).collect())
}

/// Whether `name` matches `pattern`, where `*` matches any run of characters (also empty) and
/// `?` exactly one; everything else matches itself. Greedy with backtracking to the last `*`,
/// linear in practice.
pub fn wildcard_match(pattern: &str, name: &str) -> bool {
    let p: Vec<char> = pattern.chars().collect();
    let n: Vec<char> = name.chars().collect();
    let (mut i, mut j) = (0, 0);
    // Position after the last `*` seen, and the name position it was tried at.
    let mut star: Option<(usize, usize)> = None;
    while j < n.len() {
        match p.get(i) {
            Some('*') => {
                star = Some((i + 1, j));
                i += 1;
            }
            Some(&c) if c == '?' || c == n[j] => {
                i += 1;
                j += 1;
            }
            _ => match star {
                Some((after, tried)) => {
                    i = after;
                    j = tried + 1;
                    star = Some((after, tried + 1));
                }
                None => return false,
            },
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

/// Natural order: digit runs compare as numbers (then by length, fewer leading zeros first),
/// other characters as themselves; ties fall back to plain string order.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (mut x, mut y) = (a.as_bytes(), b.as_bytes());
    loop {
        match (x.first(), y.first()) {
            (None, None) => return a.cmp(b),
            (None, Some(_)) => return Ordering::Less,
            (Some(_), None) => return Ordering::Greater,
            (Some(c), Some(d)) if c.is_ascii_digit() && d.is_ascii_digit() => {
                let run = |s: &[u8]| s.iter().take_while(|c| c.is_ascii_digit()).count();
                let (lx, ly) = (run(x), run(y));
                let (dx, dy) = (&x[..lx], &y[..ly]);
                let strip = |s: &[u8]| {
                    let zeros = s.iter().take_while(|&&c| c == b'0').count();
                    s.len() - zeros
                };
                let (sx, sy) = (strip(dx), strip(dy));
                let by_value = sx
                    .cmp(&sy)
                    .then_with(|| dx[lx - sx..].cmp(&dy[ly - sy..]))
                    .then_with(|| lx.cmp(&ly));
                if by_value != Ordering::Equal {
                    return by_value;
                }
                x = &x[lx..];
                y = &y[ly..];
            }
            (Some(c), Some(d)) => {
                if c != d {
                    return c.cmp(d);
                }
                x = &x[1..];
                y = &y[1..];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::image_io::write_image;
    use ocellus_engine::value::{Channels, Image};

    fn ctx() -> RunContext {
        RunContext {
            node: "seq".into(),
            threads: 1,
            element: None,
        }
    }

    /// A fresh temporary folder, removed when dropped.
    struct TempDir(PathBuf);

    impl TempDir {
        fn new(tag: &str) -> TempDir {
            let dir = std::env::temp_dir().join(format!(
                "ocellus-seq-{tag}-{}-{:?}",
                std::process::id(),
                std::thread::current().id()
            ));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            TempDir(dir)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn frame(v: u8) -> Image {
        Image::from_u8(2, 1, Channels::Gray, vec![v, v]).unwrap()
    }

    fn op(path: PathBuf, start: u32, step: u32, limit: Option<u32>) -> Sequence {
        Sequence::new(SequenceParams {
            path,
            start,
            step,
            limit,
            fps: 30.0,
        })
        .unwrap()
    }

    /// The first sample of every frame, and the count.
    fn run(op: &Sequence) -> Result<(Vec<u8>, i64), OpError> {
        let mut out = op.run(&ctx(), &Inputs::new(&[], &[]))?;
        let Some(Value::List(list)) = out.take("frames") else {
            panic!("expected a list");
        };
        let Some(Value::Integer(count)) = out.take("count") else {
            panic!("expected a count");
        };
        let firsts = list
            .items
            .iter()
            .map(|v| match v {
                Value::Image(i) => i.as_u8().unwrap()[0],
                _ => panic!("expected images"),
            })
            .collect();
        Ok((firsts, count))
    }

    #[test]
    fn wildcards() {
        assert!(wildcard_match("*.png", "a.png"));
        assert!(wildcard_match("*.png", ".png"));
        assert!(!wildcard_match("*.png", "a.png.bak"));
        assert!(wildcard_match("f??.png", "f01.png"));
        assert!(!wildcard_match("f??.png", "f1.png"));
        assert!(wildcard_match("*", ""));
        assert!(wildcard_match("a*b*c", "aXXbYYbc"));
        assert!(!wildcard_match("a*b*c", "aXXcYYb"));
        assert!(wildcard_match("**x", "x"));
        assert!(wildcard_match("exact.png", "exact.png"));
        assert!(!wildcard_match("exact.png", "Exact.png"));
        assert!(wildcard_match("é?*", "éèà"));
    }

    /// Wildcard matching by its recursive definition.
    fn reference_match(p: &[char], n: &[char]) -> bool {
        match p.first() {
            None => n.is_empty(),
            Some('*') => {
                reference_match(&p[1..], n) || (!n.is_empty() && reference_match(p, &n[1..]))
            }
            Some('?') => !n.is_empty() && reference_match(&p[1..], &n[1..]),
            Some(c) => n.first() == Some(c) && reference_match(&p[1..], &n[1..]),
        }
    }

    proptest::proptest! {
        #[test]
        fn wildcards_match_the_definition(p in "[ab*?]{0,7}", n in "[ab]{0,9}") {
            let (pc, nc): (Vec<char>, Vec<char>) = (p.chars().collect(), n.chars().collect());
            proptest::prop_assert_eq!(wildcard_match(&p, &n), reference_match(&pc, &nc));
        }

        #[test]
        fn numbered_names_sort_by_number(a: u64, b: u64, zeros in 0usize..3) {
            let pad = "0".repeat(zeros);
            let (x, y) = (format!("img_{pad}{a}.png"), format!("img_{b}.png"));
            let expected = a.cmp(&b).then(zeros.cmp(&0));
            proptest::prop_assert_eq!(natural_cmp(&x, &y), expected);
            proptest::prop_assert_eq!(natural_cmp(&y, &x), expected.reverse());
        }
    }

    #[test]
    fn natural_order() {
        let mut names = vec![
            "frame10.png",
            "frame2.png",
            "frame1.png",
            "frame02.png",
            "frame.png",
            "a100b3",
            "a100b20",
            "frame1a.png",
        ];
        names.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            names,
            [
                "a100b3",
                "a100b20",
                "frame.png",
                "frame1.png",
                "frame1a.png",
                "frame2.png",
                "frame02.png",
                "frame10.png"
            ]
        );
        assert_eq!(natural_cmp("x9", "x10"), Ordering::Less);
        assert_eq!(natural_cmp("x", "x"), Ordering::Equal);
        assert_eq!(
            natural_cmp("18446744073709551616000", "9"),
            Ordering::Greater
        );
    }

    #[test]
    fn as_a_stream_source_it_decodes_the_same_frames_one_at_a_time() {
        let dir = TempDir::new("stream");
        for k in [3u8, 1, 2, 10] {
            write_image(&dir.0.join(format!("f{k}.png")), &frame(k)).unwrap();
        }
        let sequence = op(dir.0.join("f*.png"), 1, 1, None);
        let mut source = sequence
            .frame_source(&ctx(), &Inputs::new(&[], &[]))
            .unwrap()
            .unwrap();
        assert_eq!(source.frames(), 3);
        // 30 fps: frame k at k/30 s.
        assert_eq!(
            (0..3).map(|k| source.timestamp_us(k)).collect::<Vec<_>>(),
            [0, 33_333, 66_667]
        );
        let statics = source.statics(&ctx()).unwrap();
        assert_eq!(statics.get("count"), Some(&Value::Integer(3)));
        let mut batch = sequence.run(&ctx(), &Inputs::new(&[], &[])).unwrap();
        let Some(Value::List(frames)) = batch.take("frames") else {
            panic!("expected frames");
        };
        let Some(Value::List(names)) = batch.take("names") else {
            panic!("expected names");
        };
        for k in 0..3 {
            let mut one = source.frame(&ctx(), k).unwrap();
            assert_eq!(one.take("frames").as_ref(), frames.items.get(k));
            assert_eq!(one.take("names").as_ref(), names.items.get(k));
        }
        assert!(source.frame(&ctx(), 3).is_err());
    }

    #[test]
    fn reads_a_pattern_in_natural_order_with_start_step_limit() {
        let dir = TempDir::new("pattern");
        for k in [1u8, 2, 3, 10, 11, 20] {
            write_image(&dir.0.join(format!("f{k}.png")), &frame(k)).unwrap();
        }
        write_image(&dir.0.join("other7.png"), &frame(7)).unwrap();
        std::fs::write(dir.0.join("f5.txt"), b"not an image").unwrap();
        let pattern = dir.0.join("f*.png");
        assert_eq!(
            run(&op(pattern.clone(), 0, 1, None)).unwrap(),
            (vec![1, 2, 3, 10, 11, 20], 6)
        );
        assert_eq!(
            run(&op(pattern.clone(), 1, 2, None)).unwrap(),
            (vec![2, 10, 20], 3)
        );
        assert_eq!(
            run(&op(pattern.clone(), 1, 2, Some(2))).unwrap(),
            (vec![2, 10], 2)
        );
        let mut out = op(pattern.clone(), 1, 2, None)
            .run(&ctx(), &Inputs::new(&[], &[]))
            .unwrap();
        assert_eq!(
            out.take("names"),
            Some(Value::list(
                PortType::Text,
                ["f2.png", "f10.png", "f20.png"]
                    .map(|n| Value::Text(n.into()))
                    .to_vec()
            ))
        );
        assert_eq!(
            run(&op(dir.0.join("f?.png"), 0, 1, None)).unwrap(),
            (vec![1, 2, 3], 3)
        );
        let err = run(&op(pattern, 6, 1, None)).unwrap_err().to_string();
        assert!(err.contains("beyond the 6"), "{err}");
    }

    #[test]
    fn a_folder_takes_image_files_of_any_size() {
        let dir = TempDir::new("folder");
        write_image(&dir.0.join("b.png"), &frame(2)).unwrap();
        let big = Image::from_u8(3, 2, Channels::Rgb, vec![9; 18]).unwrap();
        write_image(&dir.0.join("c.PPM"), &big).unwrap();
        write_image(&dir.0.join("a.tif"), &frame(1)).unwrap();
        write_image(&dir.0.join(".hidden.png"), &frame(5)).unwrap();
        std::fs::write(dir.0.join("notes.txt"), b"x").unwrap();
        std::fs::create_dir(dir.0.join("sub.png")).unwrap();
        let mut out = op(dir.0.clone(), 0, 1, None)
            .run(&ctx(), &Inputs::new(&[], &[]))
            .unwrap();
        let Some(Value::List(list)) = out.take("frames") else {
            panic!("expected a list");
        };
        assert_eq!(list.items.len(), 3);
        assert_eq!(list.items[0], Value::image(frame(1)));
        assert_eq!(list.items[1], Value::image(frame(2)));
        assert_eq!(list.items[2], Value::image(big));
        let Some(Value::List(names)) = out.take("names") else {
            panic!("expected names");
        };
        assert_eq!(names.element, PortType::Text);
        let names: Vec<&str> = names
            .items
            .iter()
            .map(|v| match v {
                Value::Text(t) => &**t,
                _ => panic!("expected text"),
            })
            .collect();
        assert_eq!(names, ["a.tif", "b.png", "c.PPM"]);
    }

    #[test]
    fn errors_name_the_pattern_folder_and_file() {
        let dir = TempDir::new("errors");
        let err = run(&op(dir.0.join("*.png"), 0, 1, None))
            .unwrap_err()
            .to_string();
        assert!(err.contains("no file matches `*.png`"), "{err}");
        assert!(err.contains(&dir.0.display().to_string()), "{err}");
        let err = run(&op(dir.0.clone(), 0, 1, None)).unwrap_err().to_string();
        assert!(err.contains("no image file"), "{err}");
        write_image(&dir.0.join("good1.png"), &frame(1)).unwrap();
        std::fs::write(dir.0.join("good2.png"), b"\x89PNG\r\n\x1a\ntruncated").unwrap();
        let err = run(&op(dir.0.join("good*.png"), 0, 1, None))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("frame 1") && err.contains("good2.png"),
            "{err}"
        );
        let missing = op(PathBuf::from("/nonexistent/ocellus/*.png"), 0, 1, None);
        assert!(run(&missing).is_err());
        assert!(missing.fingerprint().is_err());
    }

    #[test]
    fn fingerprint_follows_contents_and_listing() {
        let dir = TempDir::new("fingerprint");
        write_image(&dir.0.join("s1.png"), &frame(1)).unwrap();
        write_image(&dir.0.join("s2.png"), &frame(2)).unwrap();
        let seq = op(dir.0.join("s*.png"), 0, 1, None);
        let a = seq.fingerprint().unwrap();
        assert_eq!(seq.fingerprint().unwrap(), a);
        write_image(&dir.0.join("s2.png"), &frame(3)).unwrap();
        let b = seq.fingerprint().unwrap();
        assert_ne!(a, b);
        write_image(&dir.0.join("s3.png"), &frame(3)).unwrap();
        let c = seq.fingerprint().unwrap();
        assert_ne!(b, c);
        std::fs::rename(dir.0.join("s3.png"), dir.0.join("s4.png")).unwrap();
        assert_ne!(seq.fingerprint().unwrap(), c);
        // A file outside the selection does not matter.
        let first = op(dir.0.join("s*.png"), 0, 1, Some(1));
        let d = first.fingerprint().unwrap();
        write_image(&dir.0.join("s4.png"), &frame(9)).unwrap();
        assert_eq!(first.fingerprint().unwrap(), d);
    }

    #[test]
    fn new_checks_params() {
        let p = |path: &str, step, limit| SequenceParams {
            path: PathBuf::from(path),
            start: 0,
            step,
            limit,
            fps: 30.0,
        };
        assert!(Sequence::new(p("frames/*.png", 1, None)).is_ok());
        assert!(Sequence::new(p("", 1, None)).is_err());
        assert!(Sequence::new(p("a/*.png", 0, None)).is_err());
        assert!(Sequence::new(p("a/*.png", 1, Some(0))).is_err());
        let err = Sequence::new(p("a*/x.png", 1, None)).unwrap_err();
        assert!(err.contains("last component"), "{err}");
    }
}
