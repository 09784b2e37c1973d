//! Frame sequences as animated files: GIF (the `gif` crate; an exact palette when a frame has
//! at most 256 colours, NeuQuant otherwise) and APNG (the `png` crate, lossless RGBA).
//!
//! Frames are encoded as they arrive and the file is written atomically when the sequence is
//! finished, so an interrupted run leaves no partial animation. Pixels convert to 8-bit sRGB
//! RGBA: u8 as stored, u16 scaled by 255/65535, f32 taken as linear light and sRGB-encoded
//! (clamped to 0..1, NaN → 0), as every f32 colour image of the renderers is; gray repeats into
//! R, G and B.

use std::path::{Path, PathBuf};

use crate::image_io::write_atomic;
use crate::mesh_write::linear_to_srgb;
use crate::timeline::Encoding;
use crate::value::{Channels, Image, PixelData};

/// GIF's largest width or height.
const GIF_MAX_SIDE: usize = u16::MAX as usize;
/// NeuQuant speed (1 best … 30 fastest) for frames with more than 256 colours.
const GIF_QUANTIZE_SPEED: i32 = 10;

/// Why an animation could not be written.
#[derive(Debug, thiserror::Error)]
pub enum SequenceError {
    /// A frame's size differs from the first frame's.
    #[error(
        "{path}: frame {frame} is {width}×{height}, but the first frame is {first_width}×{first_height}"
    )]
    FrameSize {
        /// Target file.
        path: PathBuf,
        /// Frame position.
        frame: usize,
        /// This frame's width.
        width: usize,
        /// This frame's height.
        height: usize,
        /// The first frame's width.
        first_width: usize,
        /// The first frame's height.
        first_height: usize,
    },
    /// The frames cannot be stored in this format.
    #[error("{path}: {message}")]
    Unsupported {
        /// Target file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// Encoding or writing failed.
    #[error("{path}: {message}")]
    Write {
        /// Target file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// 8-bit sRGB RGBA pixels of an image (see the module doc for the conversion).
pub fn image_to_rgba8(image: &Image) -> Vec<u8> {
    let channels = image.channels();
    let n = image.width() * image.height();
    let to_byte: Box<dyn Fn(usize) -> u8 + '_> = match image.data() {
        PixelData::U8(d) => Box::new(move |i| d[i]),
        PixelData::U16(d) => Box::new(move |i| ((u32::from(d[i]) * 255 + 32767) / 65535) as u8),
        PixelData::F32(d) => Box::new(move |i| (linear_to_srgb(d[i]) * 255.0).round() as u8),
    };
    // Alpha of f32 images is linear coverage, not a colour: scale it without encoding.
    let alpha_byte = |i: usize| -> u8 {
        match image.data() {
            PixelData::F32(d) => {
                let a = d[i];
                if a.is_nan() {
                    0
                } else {
                    (a.clamp(0.0, 1.0) * 255.0).round() as u8
                }
            }
            _ => to_byte(i),
        }
    };
    let mut out = Vec::with_capacity(n * 4);
    for p in 0..n {
        match channels {
            Channels::Gray => {
                let g = to_byte(p);
                out.extend_from_slice(&[g, g, g, 255]);
            }
            Channels::Rgb => {
                let b = p * 3;
                out.extend_from_slice(&[to_byte(b), to_byte(b + 1), to_byte(b + 2), 255]);
            }
            Channels::Rgba => {
                let b = p * 4;
                out.extend_from_slice(&[
                    to_byte(b),
                    to_byte(b + 1),
                    to_byte(b + 2),
                    alpha_byte(b + 3),
                ]);
            }
        }
    }
    out
}

/// An animation being written. Frames are encoded as they arrive into a temp file next to the
/// target (GIF always; APNG when the frame count is known up front, see
/// [`AnimationWriter::with_frame_count`] — otherwise APNG frames wait in memory, since the
/// format's header holds the count), renamed over the target by [`finish`](Self::finish), and
/// removed if the writer is dropped unfinished.
pub struct AnimationWriter {
    path: PathBuf,
    encoding: Encoding,
    fps: f64,
    size: Option<(usize, usize)>,
    frames: usize,
    expected: Option<usize>,
    temp: Option<PathBuf>,
    gif: Option<gif::Encoder<std::io::BufWriter<std::fs::File>>>,
    apng: Option<png::Writer<std::fs::File>>,
    apng_frames: Vec<Vec<u8>>,
    last_rgba: Vec<u8>,
}

impl Drop for AnimationWriter {
    fn drop(&mut self) {
        if let Some(temp) = self.temp.take() {
            let _ = std::fs::remove_file(&temp);
            crate::temp_files::forget(&temp);
        }
    }
}

impl std::fmt::Debug for AnimationWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AnimationWriter")
            .field("path", &self.path)
            .field("encoding", &self.encoding)
            .field("frames", &self.frames)
            .finish()
    }
}

impl AnimationWriter {
    /// A writer for `path` at `fps` frames per second. GIF stores delays in hundredths of a
    /// second, so its rate is rounded to that (24 fps plays at 25).
    pub fn new(path: &Path, encoding: Encoding, fps: f64) -> AnimationWriter {
        AnimationWriter {
            path: path.to_path_buf(),
            encoding,
            fps,
            size: None,
            frames: 0,
            expected: None,
            temp: None,
            gif: None,
            apng: None,
            apng_frames: Vec::new(),
            last_rgba: Vec::new(),
        }
    }

    /// A writer that knows it will get `frames` frames, so APNG is streamed to disk too (a
    /// stream writer's memory stays flat). Fewer frames at [`finish`](Self::finish) repeat the
    /// last one (a dropped frame shows the previous picture); more are an error.
    pub fn with_frame_count(path: &Path, encoding: Encoding, fps: f64, frames: usize) -> Self {
        let mut writer = AnimationWriter::new(path, encoding, fps);
        writer.expected = Some(frames);
        writer
    }

    /// Opens the temp file the frames stream into.
    fn open_temp(&mut self) -> Result<std::fs::File, SequenceError> {
        static COUNTER: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let name = self
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let dir = match self.path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let temp = dir.join(format!(
            ".{name}.{}.{}.ocellus.part",
            std::process::id(),
            COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        ));
        let file = crate::temp_files::create(&temp).map_err(|e| self.write_error(e))?;
        self.temp = Some(temp);
        Ok(file)
    }

    fn write_error(&self, message: impl std::fmt::Display) -> SequenceError {
        SequenceError::Write {
            path: self.path.clone(),
            message: message.to_string(),
        }
    }

    /// Adds the next frame.
    pub fn push(&mut self, image: &Image) -> Result<(), SequenceError> {
        let (width, height) = (image.width(), image.height());
        match self.size {
            None => {
                if width == 0 || height == 0 {
                    return Err(SequenceError::Unsupported {
                        path: self.path.clone(),
                        message: format!("frame 0 is {width}×{height}: an animation needs pixels"),
                    });
                }
                if self.encoding == Encoding::Gif && (width > GIF_MAX_SIDE || height > GIF_MAX_SIDE)
                {
                    return Err(SequenceError::Unsupported {
                        path: self.path.clone(),
                        message: format!(
                            "GIF frames are at most {GIF_MAX_SIDE} pixels a side, this is {width}×{height}"
                        ),
                    });
                }
                if u32::try_from(width).is_err() || u32::try_from(height).is_err() {
                    return Err(SequenceError::Unsupported {
                        path: self.path.clone(),
                        message: format!("{width}×{height} is too large"),
                    });
                }
                self.size = Some((width, height));
            }
            Some((w, h)) if (w, h) != (width, height) => {
                return Err(SequenceError::FrameSize {
                    path: self.path.clone(),
                    frame: self.frames,
                    width,
                    height,
                    first_width: w,
                    first_height: h,
                });
            }
            Some(_) => {}
        }
        let mut rgba = image_to_rgba8(image);
        match self.encoding {
            Encoding::Gif => {
                // Sizes were checked against GIF_MAX_SIDE above.
                let (w16, h16) = (width as u16, height as u16);
                if self.gif.is_none() {
                    let out = std::io::BufWriter::new(self.open_temp()?);
                    let mut encoder =
                        gif::Encoder::new(out, w16, h16, &[]).map_err(|e| self.write_error(e))?;
                    encoder
                        .set_repeat(gif::Repeat::Infinite)
                        .map_err(|e| self.write_error(e))?;
                    self.gif = Some(encoder);
                }
                if self.expected.is_some() {
                    self.last_rgba = rgba.clone(); // for `repeat_last`
                }
                let mut frame =
                    gif::Frame::from_rgba_speed(w16, h16, &mut rgba, GIF_QUANTIZE_SPEED);
                frame.delay = gif_delay_cs(self.fps);
                let result = match self.gif.as_mut() {
                    Some(encoder) => encoder.write_frame(&frame).map_err(|e| e.to_string()),
                    None => Err("GIF encoder missing".to_string()),
                };
                result.map_err(|e| self.write_error(e))?;
            }
            Encoding::Apng => match self.expected {
                Some(count) => {
                    if self.frames >= count {
                        return Err(
                            self.write_error(format!("more than the {count} frames announced"))
                        );
                    }
                    if self.apng.is_none() {
                        let out = self.open_temp()?;
                        self.apng = Some(self.apng_header(out, width, height, count)?);
                    }
                    let result = match self.apng.as_mut() {
                        Some(writer) => writer.write_image_data(&rgba).map_err(|e| e.to_string()),
                        None => Err("APNG writer missing".to_string()),
                    };
                    result.map_err(|e| self.write_error(e))?;
                    self.last_rgba = rgba;
                }
                None => self.apng_frames.push(rgba),
            },
            Encoding::Png => {
                return Err(SequenceError::Unsupported {
                    path: self.path.clone(),
                    message: "a PNG sequence is written frame by frame, not as one file".into(),
                });
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// Adds the previous frame again (a stream's dropped frame). Errors before the first.
    pub fn repeat_last(&mut self) -> Result<(), SequenceError> {
        if self.frames == 0 {
            return Err(self.write_error("no frame to repeat"));
        }
        match self.encoding {
            Encoding::Apng if self.apng.is_some() => {
                let last = std::mem::take(&mut self.last_rgba);
                let result = match self.apng.as_mut() {
                    Some(writer) => writer.write_image_data(&last).map_err(|e| e.to_string()),
                    None => Err("APNG writer missing".to_string()),
                };
                self.last_rgba = last;
                result.map_err(|e| self.write_error(e))?;
            }
            Encoding::Apng => {
                let last = self.apng_frames.last().cloned().unwrap_or_default();
                self.apng_frames.push(last);
            }
            Encoding::Gif => {
                let (w, h) = self.size.unwrap_or((0, 0));
                let mut rgba = self.last_rgba.clone();
                // Sizes were checked against GIF_MAX_SIDE in `push`.
                let mut frame =
                    gif::Frame::from_rgba_speed(w as u16, h as u16, &mut rgba, GIF_QUANTIZE_SPEED);
                frame.delay = gif_delay_cs(self.fps);
                let result = match self.gif.as_mut() {
                    Some(encoder) => encoder.write_frame(&frame).map_err(|e| e.to_string()),
                    None => Err("GIF encoder missing".to_string()),
                };
                result.map_err(|e| self.write_error(e))?;
            }
            Encoding::Png => return Err(self.write_error("not an animation format")),
        }
        self.frames += 1;
        Ok(())
    }

    /// Frames added so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Encodes and writes the file atomically; returns its path.
    pub fn finish(mut self) -> Result<PathBuf, SequenceError> {
        let Some((width, height)) = self.size else {
            return Err(SequenceError::Unsupported {
                path: self.path.clone(),
                message: "no frames".into(),
            });
        };
        match self.encoding {
            Encoding::Gif => {
                let encoder = self
                    .gif
                    .take()
                    .ok_or_else(|| self.write_error("GIF encoder missing"))?;
                let out = encoder.into_inner().map_err(|e| self.write_error(e))?;
                let file = out.into_inner().map_err(|e| self.write_error(e.error()))?;
                file.sync_all().map_err(|e| self.write_error(e))?;
                drop(file);
                self.commit()?;
            }
            Encoding::Apng if self.apng.is_some() => {
                let count = self.expected.unwrap_or(self.frames);
                let last = std::mem::take(&mut self.last_rgba);
                let mut writer = self
                    .apng
                    .take()
                    .ok_or_else(|| self.write_error("APNG writer missing"))?;
                for _ in self.frames..count {
                    writer
                        .write_image_data(&last)
                        .map_err(|e| self.write_error(e))?;
                }
                // `finish` writes the end chunk and closes the file.
                writer.finish().map_err(|e| self.write_error(e))?;
                if let Some(temp) = &self.temp {
                    std::fs::File::open(temp)
                        .and_then(|f| f.sync_all())
                        .map_err(|e| self.write_error(e))?;
                }
                self.commit()?;
            }
            Encoding::Apng => {
                let bytes = self.encode_apng(width, height)?;
                write_atomic(&self.path, &bytes).map_err(|e| self.write_error(e))?;
            }
            Encoding::Png => return Err(self.write_error("not an animation format")),
        }
        Ok(self.path.clone())
    }

    /// Renames the (synced, closed) temp file over the target.
    fn commit(&mut self) -> Result<(), SequenceError> {
        let temp = self
            .temp
            .take()
            .ok_or_else(|| self.write_error("temp file missing"))?;
        let renamed = std::fs::rename(&temp, &self.path);
        if renamed.is_err() {
            let _ = std::fs::remove_file(&temp);
        }
        crate::temp_files::forget(&temp);
        renamed.map_err(|e| self.write_error(e))
    }

    fn apng_header<W: std::io::Write>(
        &self,
        out: W,
        width: usize,
        height: usize,
        count: usize,
    ) -> Result<png::Writer<W>, SequenceError> {
        let count = u32::try_from(count).map_err(|e| self.write_error(e))?;
        let err = |e: png::EncodingError| self.write_error(e);
        // Sizes were checked to fit u32 in `push`.
        let mut encoder = png::Encoder::new(out, width as u32, height as u32);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_animated(count, 0).map_err(err)?;
        let (num, den) = apng_delay(self.fps);
        encoder.set_frame_delay(num, den).map_err(err)?;
        encoder.write_header().map_err(err)
    }

    fn encode_apng(&self, width: usize, height: usize) -> Result<Vec<u8>, SequenceError> {
        let mut bytes = Vec::new();
        {
            let mut writer = self.apng_header(&mut bytes, width, height, self.apng_frames.len())?;
            for frame in &self.apng_frames {
                writer
                    .write_image_data(frame)
                    .map_err(|e| self.write_error(e))?;
            }
            writer.finish().map_err(|e| self.write_error(e))?;
        }
        Ok(bytes)
    }
}

/// Writes the outputs of an animation's frames into a folder (`ocellus run G.ron --emit DIR` on
/// an animated graph). The layout is a contract, like [`crate::emit`]'s:
///
/// | output | files |
/// |--------|-------|
/// | any | `NAME/F` per frame, `F` the frame's position zero-padded to the width of the last one (`00` … `47`), each written as [`crate::emit::emit_value`] writes it |
/// | Image | also `NAME.gif`, `NAME.apng` and/or `NAME_png/F.png` (8-bit sRGB), as the output's `encode` entry says (GIF by default) |
/// | Metrics | also `NAME.csv`: a header `frame,time_s,KEY…` (keys sorted, over all frames) and one row per frame; a key a frame lacks is an empty cell; numbers in shortest round-trip form, `NaN`/`inf`/`-inf` for non-finite ones |
///
/// A frame whose output failed is skipped in that output's files.
pub struct FrameEmitter {
    dir: PathBuf,
    digits: usize,
    fps: f64,
    /// Frames announced (a stream's source length): APNG streams to disk and dropped frames
    /// are filled; `None` for animations.
    expected: Option<usize>,
    encodings: std::collections::BTreeMap<String, Vec<Encoding>>,
    metrics: Vec<crate::stream::MetricsFormat>,
    writers: std::collections::BTreeMap<String, Vec<AnimationWriter>>,
    tables: std::collections::BTreeMap<String, Vec<(i64, f64, crate::value::Metrics)>>,
    lines: std::collections::BTreeMap<String, JsonLines>,
    written: Vec<PathBuf>,
}

/// A JSON-lines file being written: a temp file renamed at the end.
struct JsonLines {
    temp: PathBuf,
    path: PathBuf,
    out: std::io::BufWriter<std::fs::File>,
}

impl FrameEmitter {
    /// An emitter for `animated`'s frames into `dir`.
    pub fn new(dir: &Path, animated: &crate::timeline::Animated) -> FrameEmitter {
        FrameEmitter {
            dir: dir.to_path_buf(),
            digits: animated.frames.saturating_sub(1).to_string().len(),
            fps: animated.fps,
            expected: None,
            encodings: animated.encode.clone(),
            metrics: vec![crate::stream::MetricsFormat::Csv],
            writers: std::collections::BTreeMap::new(),
            tables: std::collections::BTreeMap::new(),
            lines: std::collections::BTreeMap::new(),
            written: Vec::new(),
        }
    }

    /// An emitter for a stream of `frames` source frames at `fps` (the animation files' rate)
    /// into `dir`, with the stream section's encodings and metrics formats. Files are named by
    /// the frame's source index, so a dropped frame leaves a gap (and holds the previous
    /// picture in GIF/APNG). `NAME.jsonl` holds one object `{"frame", "time_s", KEY…}` per
    /// frame (non-finite numbers as `null`), appended as frames arrive.
    pub fn for_stream(
        dir: &Path,
        spec: &crate::stream::StreamSpec,
        frames: usize,
        fps: f64,
    ) -> FrameEmitter {
        FrameEmitter {
            dir: dir.to_path_buf(),
            digits: frames.saturating_sub(1).to_string().len(),
            fps,
            expected: Some(frames),
            encodings: spec.encode.clone(),
            metrics: spec.metrics.clone(),
            writers: std::collections::BTreeMap::new(),
            tables: std::collections::BTreeMap::new(),
            lines: std::collections::BTreeMap::new(),
            written: Vec::new(),
        }
    }

    /// Writes one frame's outputs.
    pub fn frame(&mut self, run: &crate::timeline::FrameRun) -> Result<(), String> {
        self.outputs(run.index, run.frame, run.time, &run.report.outputs)
    }

    /// Writes one stream packet's outputs.
    pub fn packet(&mut self, frame: &crate::stream::StreamFrame) -> Result<(), String> {
        let packet = frame.packet;
        self.outputs(
            packet.index,
            packet.index as i64,
            packet.timestamp_us as f64 / 1e6,
            &frame.outputs,
        )
    }

    /// Writes the outputs of frame `index` (number `frame`, at `time` s).
    fn outputs(
        &mut self,
        index: usize,
        frame: i64,
        time: f64,
        outputs: &[(String, crate::value::Value)],
    ) -> Result<(), String> {
        let mut failed = Vec::new();
        for (name, value) in outputs {
            let element = format!("{index:0width$}", width = self.digits);
            match crate::emit::emit_value(&self.dir.join(name), &element, value) {
                Ok(files) => self.written.extend(files),
                Err(e) => failed.push(format!("output `{name}`, frame {frame}: {e}")),
            }
            match value {
                crate::value::Value::Image(image) => {
                    let encodings = self
                        .encodings
                        .get(name)
                        .cloned()
                        .unwrap_or_else(|| vec![Encoding::Gif]);
                    if encodings.contains(&Encoding::Png) {
                        let folder = self.dir.join(format!("{name}_png"));
                        let path = folder.join(format!("{element}.png"));
                        match std::fs::create_dir_all(&folder)
                            .map_err(|e| e.to_string())
                            .and_then(|()| write_png_frame(&path, image))
                        {
                            Ok(()) => self.written.push(path),
                            Err(e) => failed.push(format!("{}: {e}", path.display())),
                        }
                    }
                    let (dir, fps, expected) = (&self.dir, self.fps, self.expected);
                    let writers = self.writers.entry(name.clone()).or_insert_with(|| {
                        encodings
                            .into_iter()
                            .filter(|e| *e != Encoding::Png)
                            .map(|e| {
                                let path = dir.join(format!("{name}.{}", e.extension()));
                                match expected {
                                    Some(n) => AnimationWriter::with_frame_count(&path, e, fps, n),
                                    None => AnimationWriter::new(&path, e, fps),
                                }
                            })
                            .collect()
                    });
                    for w in writers {
                        // A dropped frame holds the previous picture.
                        while expected.is_some() && w.frames() < index && w.frames() > 0 {
                            if let Err(e) = w.repeat_last() {
                                failed.push(e.to_string());
                                break;
                            }
                        }
                        if let Err(e) = w.push(image) {
                            failed.push(e.to_string());
                        }
                    }
                }
                crate::value::Value::Metrics(m) => {
                    if self.metrics.contains(&crate::stream::MetricsFormat::Csv) {
                        self.tables.entry(name.clone()).or_default().push((
                            frame,
                            time,
                            (**m).clone(),
                        ));
                    }
                    if self.metrics.contains(&crate::stream::MetricsFormat::Jsonl)
                        && let Err(e) = self.json_line(name, frame, time, m)
                    {
                        failed.push(e);
                    }
                }
                _ => {}
            }
        }
        if failed.is_empty() {
            Ok(())
        } else {
            Err(failed.join("\n"))
        }
    }

    fn json_line(
        &mut self,
        name: &str,
        frame: i64,
        time: f64,
        metrics: &crate::value::Metrics,
    ) -> Result<(), String> {
        use std::io::Write;
        if !self.lines.contains_key(name) {
            let path = self.dir.join(format!("{name}.jsonl"));
            let temp = self
                .dir
                .join(format!(".{name}.jsonl.{}.ocellus.part", std::process::id()));
            // Left over only by a run killed outright; a new run replaces it.
            let _ = std::fs::remove_file(&temp);
            let file =
                crate::temp_files::create(&temp).map_err(|e| format!("{}: {e}", temp.display()))?;
            self.lines.insert(
                name.to_string(),
                JsonLines {
                    temp,
                    path,
                    out: std::io::BufWriter::new(file),
                },
            );
        }
        let number = |x: f64| {
            serde_json::Number::from_f64(x)
                .map_or(serde_json::Value::Null, serde_json::Value::Number)
        };
        let mut object = serde_json::Map::new();
        object.insert("frame".into(), serde_json::Value::from(frame));
        object.insert("time_s".into(), number(time));
        for (k, v) in metrics {
            object.insert(k.clone(), number(*v));
        }
        let line = serde_json::Value::Object(object).to_string();
        let Some(file) = self.lines.get_mut(name) else {
            return Err(format!("{name}.jsonl is not open"));
        };
        writeln!(file.out, "{line}").map_err(|e| format!("{}: {e}", file.path.display()))
    }

    /// Finishes the animations and tables; returns every file written.
    pub fn finish(mut self) -> Result<Vec<PathBuf>, String> {
        let mut failed = Vec::new();
        for writer in std::mem::take(&mut self.writers).into_values().flatten() {
            match writer.finish() {
                Ok(path) => self.written.push(path),
                Err(e) => failed.push(e.to_string()),
            }
        }
        for (name, rows) in std::mem::take(&mut self.tables) {
            let path = self.dir.join(format!("{name}.csv"));
            match write_atomic(&path, metrics_csv(&rows).as_bytes()) {
                Ok(()) => self.written.push(path),
                Err(e) => failed.push(format!("{}: {e}", path.display())),
            }
        }
        for (_, lines) in std::mem::take(&mut self.lines) {
            let JsonLines { temp, path, out } = lines;
            let done = out
                .into_inner()
                .map_err(|e| e.error().to_string())
                .and_then(|f| f.sync_all().map_err(|e| e.to_string()))
                .and_then(|()| std::fs::rename(&temp, &path).map_err(|e| e.to_string()));
            if done.is_err() {
                let _ = std::fs::remove_file(&temp);
            }
            crate::temp_files::forget(&temp);
            match done {
                Ok(()) => self.written.push(path),
                Err(e) => failed.push(format!("{}: {e}", path.display())),
            }
        }
        if failed.is_empty() {
            Ok(std::mem::take(&mut self.written))
        } else {
            Err(failed.join("\n"))
        }
    }
}

impl Drop for FrameEmitter {
    fn drop(&mut self) {
        for lines in self.lines.values() {
            let _ = std::fs::remove_file(&lines.temp);
            crate::temp_files::forget(&lines.temp);
        }
    }
}

/// One frame as an 8-bit sRGB PNG (RGB, or RGBA for images with alpha), written atomically.
fn write_png_frame(path: &Path, image: &Image) -> Result<(), String> {
    let rgba = image_to_rgba8(image);
    let (data, color) = if image.channels() == Channels::Rgba {
        (rgba, png::ColorType::Rgba)
    } else {
        let rgb: Vec<u8> = rgba
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect();
        (rgb, png::ColorType::Rgb)
    };
    let (w, h) = (
        u32::try_from(image.width()).map_err(|e| e.to_string())?,
        u32::try_from(image.height()).map_err(|e| e.to_string())?,
    );
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, w, h);
        encoder.set_color(color);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        writer.write_image_data(&data).map_err(|e| e.to_string())?;
        writer.finish().map_err(|e| e.to_string())?;
    }
    write_atomic(path, &bytes).map_err(|e| e.to_string())
}

fn csv_number(x: f64) -> String {
    if x.is_nan() {
        "NaN".into()
    } else if x.is_infinite() {
        if x > 0.0 { "inf".into() } else { "-inf".into() }
    } else {
        format!("{x}")
    }
}

/// The CSV text of per-frame metrics (see [`FrameEmitter`]).
pub fn metrics_csv(rows: &[(i64, f64, crate::value::Metrics)]) -> String {
    let keys: std::collections::BTreeSet<&String> =
        rows.iter().flat_map(|(_, _, m)| m.keys()).collect();
    let mut out = String::from("frame,time_s");
    for k in &keys {
        out.push(',');
        // Metric names are identifiers; quote any that are not, per RFC 4180.
        if k.contains([',', '"', '\n']) {
            out.push_str(&format!("\"{}\"", k.replace('"', "\"\"")));
        } else {
            out.push_str(k);
        }
    }
    out.push('\n');
    for (frame, time, m) in rows {
        out.push_str(&format!("{frame},{}", csv_number(*time)));
        for k in &keys {
            out.push(',');
            if let Some(v) = m.get(*k) {
                out.push_str(&csv_number(*v));
            }
        }
        out.push('\n');
    }
    out
}

/// GIF frame delay in hundredths of a second (at least 1).
pub fn gif_delay_cs(fps: f64) -> u16 {
    let cs = (100.0 / fps).round();
    if cs.is_finite() {
        cs.clamp(1.0, f64::from(u16::MAX)) as u16
    } else {
        1
    }
}

/// APNG frame delay as a fraction of a second: `1/fps` for whole rates, else milliseconds.
pub fn apng_delay(fps: f64) -> (u16, u16) {
    if fps.fract() == 0.0 && (1.0..=f64::from(u16::MAX)).contains(&fps) {
        (1, fps as u16)
    } else {
        let ms = (1000.0 / fps).round();
        let ms = if ms.is_finite() {
            ms.clamp(1.0, f64::from(u16::MAX))
        } else {
            1.0
        };
        (ms as u16, 1000)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn gradient(width: usize, height: usize, phase: u8) -> Image {
        let mut data = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            for x in 0..width {
                data.extend_from_slice(&[
                    (x * 255 / width.max(1)) as u8,
                    (y * 255 / height.max(1)) as u8,
                    phase,
                ]);
            }
        }
        Image::new(width, height, Channels::Rgb, PixelData::U8(data)).unwrap()
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("ocellus-seq-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn conversions_hand_computed() {
        let gray = Image::new(2, 1, Channels::Gray, PixelData::U16(vec![0, 65535])).unwrap();
        assert_eq!(
            image_to_rgba8(&gray),
            vec![0, 0, 0, 255, 255, 255, 255, 255]
        );
        // Linear 0.5 is sRGB 188; NaN → 0; alpha stays linear.
        let f = Image::new(
            1,
            1,
            Channels::Rgba,
            PixelData::F32(vec![0.5, f32::NAN, 2.0, 0.5]),
        )
        .unwrap();
        assert_eq!(image_to_rgba8(&f), vec![188, 0, 255, 128]);
    }

    #[test]
    fn gif_round_trips_exact_palette_frames() {
        let dir = scratch("gif");
        let path = dir.join("a.gif");
        let mut w = AnimationWriter::new(&path, Encoding::Gif, 25.0);
        // 8×4 with ≤ 256 colours: the palette is exact, so decoding gives the pixels back.
        let frames: Vec<Image> = (0..3).map(|i| gradient(8, 4, i * 100)).collect();
        for f in &frames {
            w.push(f).unwrap();
        }
        assert_eq!(w.finish().unwrap(), path);
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options
            .read_info(std::fs::File::open(&path).unwrap())
            .unwrap();
        let mut n = 0;
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            assert_eq!(frame.delay, 4);
            assert_eq!(&frame.buffer[..], &image_to_rgba8(&frames[n])[..]);
            n += 1;
        }
        assert_eq!(n, 3);
        // No temp file left beside it.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
    }

    #[test]
    fn apng_round_trips() {
        let dir = scratch("apng");
        let path = dir.join("a.apng");
        let mut w = AnimationWriter::new(&path, Encoding::Apng, 24.0);
        let frames: Vec<Image> = (0..4).map(|i| gradient(5, 3, i * 60)).collect();
        for f in &frames {
            w.push(f).unwrap();
        }
        w.finish().unwrap();
        let decoder =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let control = reader.info().animation_control.unwrap();
        assert_eq!(control.num_frames, 4);
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        for f in &frames {
            reader.next_frame(&mut buf).unwrap();
            let fc = reader.info().frame_control.unwrap();
            assert_eq!((fc.delay_num, fc.delay_den), (1, 24));
            assert_eq!(&buf[..], &image_to_rgba8(f)[..]);
        }
    }

    #[test]
    fn mismatched_and_empty_frames_are_errors_and_write_nothing() {
        let dir = scratch("bad");
        let path = dir.join("a.gif");
        let mut w = AnimationWriter::new(&path, Encoding::Gif, 10.0);
        w.push(&gradient(4, 4, 0)).unwrap();
        let e = w.push(&gradient(5, 4, 0)).unwrap_err();
        assert!(e.to_string().contains("frame 1 is 5×4"), "{e}");
        drop(w);
        assert!(!path.exists());
        let mut w = AnimationWriter::new(&path, Encoding::Apng, 10.0);
        assert!(w.push(&gradient(0, 4, 0)).is_err());
        assert!(w.finish().is_err());
        assert!(!path.exists());
    }

    #[test]
    fn delays() {
        assert_eq!(gif_delay_cs(24.0), 4);
        assert_eq!(gif_delay_cs(10.0), 10);
        assert_eq!(gif_delay_cs(1000.0), 1);
        assert_eq!(apng_delay(30.0), (1, 30));
        assert_eq!(apng_delay(29.97), (33, 1000));
    }
}
