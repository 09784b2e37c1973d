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

/// Frames waiting to be encoded: APNG needs the frame count in its header, GIF does not, but
/// both are written at `finish`.
pub struct AnimationWriter {
    path: PathBuf,
    encoding: Encoding,
    fps: f64,
    size: Option<(usize, usize)>,
    frames: usize,
    gif: Option<gif::Encoder<Vec<u8>>>,
    apng_frames: Vec<Vec<u8>>,
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
            gif: None,
            apng_frames: Vec::new(),
        }
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
                    let mut encoder = gif::Encoder::new(Vec::new(), w16, h16, &[])
                        .map_err(|e| self.write_error(e))?;
                    encoder
                        .set_repeat(gif::Repeat::Infinite)
                        .map_err(|e| self.write_error(e))?;
                    self.gif = Some(encoder);
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
            Encoding::Apng => self.apng_frames.push(rgba),
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
        let bytes = match self.encoding {
            Encoding::Gif => match self.gif.take() {
                Some(encoder) => encoder.into_inner().map_err(|e| self.write_error(e))?,
                None => return Err(self.write_error("GIF encoder missing")),
            },
            Encoding::Apng => self.encode_apng(width, height)?,
            Encoding::Png => return Err(self.write_error("not an animation format")),
        };
        write_atomic(&self.path, &bytes).map_err(|e| self.write_error(e))?;
        Ok(self.path)
    }

    fn encode_apng(&self, width: usize, height: usize) -> Result<Vec<u8>, SequenceError> {
        let count = u32::try_from(self.apng_frames.len()).map_err(|e| self.write_error(e))?;
        let mut bytes = Vec::new();
        let err = |e: png::EncodingError| self.write_error(e);
        {
            // Sizes were checked to fit u32 in `push`.
            let mut encoder = png::Encoder::new(&mut bytes, width as u32, height as u32);
            encoder.set_color(png::ColorType::Rgba);
            encoder.set_depth(png::BitDepth::Eight);
            encoder.set_animated(count, 0).map_err(err)?;
            let (num, den) = apng_delay(self.fps);
            encoder.set_frame_delay(num, den).map_err(err)?;
            let mut writer = encoder.write_header().map_err(err)?;
            for frame in &self.apng_frames {
                writer.write_image_data(frame).map_err(err)?;
            }
            writer.finish().map_err(err)?;
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
    encodings: std::collections::BTreeMap<String, Vec<Encoding>>,
    writers: std::collections::BTreeMap<String, Vec<AnimationWriter>>,
    tables: std::collections::BTreeMap<String, Vec<(i64, f64, crate::value::Metrics)>>,
    written: Vec<PathBuf>,
}

impl FrameEmitter {
    /// An emitter for `animated`'s frames into `dir`.
    pub fn new(dir: &Path, animated: &crate::timeline::Animated) -> FrameEmitter {
        FrameEmitter {
            dir: dir.to_path_buf(),
            digits: animated.frames.saturating_sub(1).to_string().len(),
            fps: animated.fps,
            encodings: animated.encode.clone(),
            writers: std::collections::BTreeMap::new(),
            tables: std::collections::BTreeMap::new(),
            written: Vec::new(),
        }
    }

    /// Writes one frame's outputs.
    pub fn frame(&mut self, run: &crate::timeline::FrameRun) -> Result<(), String> {
        let mut failed = Vec::new();
        for (name, value) in &run.report.outputs {
            let element = format!("{:0width$}", run.index, width = self.digits);
            match crate::emit::emit_value(&self.dir.join(name), &element, value) {
                Ok(files) => self.written.extend(files),
                Err(e) => failed.push(format!("output `{name}`, frame {}: {e}", run.frame)),
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
                    let writers = self.writers.entry(name.clone()).or_insert_with(|| {
                        encodings
                            .into_iter()
                            .filter(|e| *e != Encoding::Png)
                            .map(|e| {
                                let path = self.dir.join(format!("{name}.{}", e.extension()));
                                AnimationWriter::new(&path, e, self.fps)
                            })
                            .collect()
                    });
                    for w in writers {
                        if let Err(e) = w.push(image) {
                            failed.push(e.to_string());
                        }
                    }
                }
                crate::value::Value::Metrics(m) => self
                    .tables
                    .entry(name.clone())
                    .or_default()
                    .push((run.frame, run.time, (**m).clone())),
                _ => {}
            }
        }
        if failed.is_empty() {
            Ok(())
        } else {
            Err(failed.join("\n"))
        }
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
        if failed.is_empty() {
            Ok(self.written)
        } else {
            Err(failed.join("\n"))
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
