//! Charts for `ocellus sweep`: the speed–accuracy scatter of a sweep with its Pareto front, as
//! SVG and as PNG, drawn with plotters.
//!
//! plotters' bitmap backend needs a font library to draw text (font-kit and fontconfig, or an
//! embedded TrueType file); neither fits a dependency-light binary. [`LabelledBitmap`] wraps the
//! bitmap backend and draws text itself with [`GLYPHS`], a 5×7 pixel font made for this project,
//! scaled by whole pixels — labels are crisp and the PNG is the same on every machine. The SVG
//! carries its text as `<text>` elements, drawn by the viewer's fonts.

use plotters::prelude::*;
use plotters_backend::{
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind,
    text_anchor::{HPos, VPos},
};

/// Chart size, px.
pub const SIZE: (u32, u32) = (960, 640);

/// 5×7 glyphs of ASCII 32..=126: seven rows, top first, bit 4 the leftmost column.
#[rustfmt::skip]
pub const GLYPHS: [[u8; 7]; 95] = [
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00], // ' '
    [0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x04], // '!'
    [0x0a, 0x0a, 0x00, 0x00, 0x00, 0x00, 0x00], // '"'
    [0x0a, 0x0a, 0x1f, 0x0a, 0x1f, 0x0a, 0x0a], // '#'
    [0x04, 0x0f, 0x14, 0x0e, 0x05, 0x1e, 0x04], // '$'
    [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03], // '%'
    [0x0c, 0x12, 0x14, 0x08, 0x15, 0x12, 0x0d], // '&'
    [0x04, 0x04, 0x00, 0x00, 0x00, 0x00, 0x00], // "'"
    [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02], // '('
    [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08], // ')'
    [0x00, 0x04, 0x15, 0x0e, 0x15, 0x04, 0x00], // '*'
    [0x00, 0x04, 0x04, 0x1f, 0x04, 0x04, 0x00], // '+'
    [0x00, 0x00, 0x00, 0x00, 0x0c, 0x04, 0x08], // ','
    [0x00, 0x00, 0x00, 0x1f, 0x00, 0x00, 0x00], // '-'
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x0c, 0x0c], // '.'
    [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00], // '/'
    [0x0e, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0e], // '0'
    [0x04, 0x0c, 0x04, 0x04, 0x04, 0x04, 0x0e], // '1'
    [0x0e, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1f], // '2'
    [0x1f, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0e], // '3'
    [0x02, 0x06, 0x0a, 0x12, 0x1f, 0x02, 0x02], // '4'
    [0x1f, 0x10, 0x1e, 0x01, 0x01, 0x11, 0x0e], // '5'
    [0x06, 0x08, 0x10, 0x1e, 0x11, 0x11, 0x0e], // '6'
    [0x1f, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08], // '7'
    [0x0e, 0x11, 0x11, 0x0e, 0x11, 0x11, 0x0e], // '8'
    [0x0e, 0x11, 0x11, 0x0f, 0x01, 0x02, 0x0c], // '9'
    [0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x0c, 0x00], // ':'
    [0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x04, 0x08], // ';'
    [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02], // '<'
    [0x00, 0x00, 0x1f, 0x00, 0x1f, 0x00, 0x00], // '='
    [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08], // '>'
    [0x0e, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04], // '?'
    [0x0e, 0x11, 0x01, 0x0d, 0x15, 0x15, 0x0e], // '@'
    [0x0e, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11], // 'A'
    [0x1e, 0x11, 0x11, 0x1e, 0x11, 0x11, 0x1e], // 'B'
    [0x0e, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0e], // 'C'
    [0x1c, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1c], // 'D'
    [0x1f, 0x10, 0x10, 0x1e, 0x10, 0x10, 0x1f], // 'E'
    [0x1f, 0x10, 0x10, 0x1e, 0x10, 0x10, 0x10], // 'F'
    [0x0e, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0f], // 'G'
    [0x11, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11], // 'H'
    [0x0e, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0e], // 'I'
    [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0c], // 'J'
    [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11], // 'K'
    [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1f], // 'L'
    [0x11, 0x1b, 0x15, 0x15, 0x11, 0x11, 0x11], // 'M'
    [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11], // 'N'
    [0x0e, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0e], // 'O'
    [0x1e, 0x11, 0x11, 0x1e, 0x10, 0x10, 0x10], // 'P'
    [0x0e, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0d], // 'Q'
    [0x1e, 0x11, 0x11, 0x1e, 0x14, 0x12, 0x11], // 'R'
    [0x0f, 0x10, 0x10, 0x0e, 0x01, 0x01, 0x1e], // 'S'
    [0x1f, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04], // 'T'
    [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0e], // 'U'
    [0x11, 0x11, 0x11, 0x11, 0x11, 0x0a, 0x04], // 'V'
    [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0a], // 'W'
    [0x11, 0x11, 0x0a, 0x04, 0x0a, 0x11, 0x11], // 'X'
    [0x11, 0x11, 0x11, 0x0a, 0x04, 0x04, 0x04], // 'Y'
    [0x1f, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1f], // 'Z'
    [0x0e, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0e], // '['
    [0x00, 0x10, 0x08, 0x04, 0x02, 0x01, 0x00], // '\\'
    [0x0e, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0e], // ']'
    [0x04, 0x0a, 0x11, 0x00, 0x00, 0x00, 0x00], // '^'
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1f], // '_'
    [0x08, 0x04, 0x00, 0x00, 0x00, 0x00, 0x00], // '`'
    [0x00, 0x00, 0x0e, 0x01, 0x0f, 0x11, 0x0f], // 'a'
    [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x1e], // 'b'
    [0x00, 0x00, 0x0e, 0x10, 0x10, 0x11, 0x0e], // 'c'
    [0x01, 0x01, 0x0d, 0x13, 0x11, 0x11, 0x0f], // 'd'
    [0x00, 0x00, 0x0e, 0x11, 0x1f, 0x10, 0x0e], // 'e'
    [0x06, 0x09, 0x08, 0x1c, 0x08, 0x08, 0x08], // 'f'
    [0x00, 0x0f, 0x11, 0x11, 0x0f, 0x01, 0x0e], // 'g'
    [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x11], // 'h'
    [0x04, 0x00, 0x0c, 0x04, 0x04, 0x04, 0x0e], // 'i'
    [0x02, 0x00, 0x06, 0x02, 0x02, 0x12, 0x0c], // 'j'
    [0x10, 0x10, 0x12, 0x14, 0x18, 0x14, 0x12], // 'k'
    [0x0c, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0e], // 'l'
    [0x00, 0x00, 0x1a, 0x15, 0x15, 0x11, 0x11], // 'm'
    [0x00, 0x00, 0x16, 0x19, 0x11, 0x11, 0x11], // 'n'
    [0x00, 0x00, 0x0e, 0x11, 0x11, 0x11, 0x0e], // 'o'
    [0x00, 0x00, 0x1e, 0x11, 0x1e, 0x10, 0x10], // 'p'
    [0x00, 0x00, 0x0d, 0x13, 0x0f, 0x01, 0x01], // 'q'
    [0x00, 0x00, 0x16, 0x19, 0x10, 0x10, 0x10], // 'r'
    [0x00, 0x00, 0x0e, 0x10, 0x0e, 0x01, 0x1e], // 's'
    [0x08, 0x08, 0x1c, 0x08, 0x08, 0x09, 0x06], // 't'
    [0x00, 0x00, 0x11, 0x11, 0x11, 0x13, 0x0d], // 'u'
    [0x00, 0x00, 0x11, 0x11, 0x11, 0x0a, 0x04], // 'v'
    [0x00, 0x00, 0x11, 0x11, 0x15, 0x15, 0x0a], // 'w'
    [0x00, 0x00, 0x11, 0x0a, 0x04, 0x0a, 0x11], // 'x'
    [0x00, 0x00, 0x11, 0x11, 0x0f, 0x01, 0x0e], // 'y'
    [0x00, 0x00, 0x1f, 0x02, 0x04, 0x08, 0x1f], // 'z'
    [0x02, 0x04, 0x04, 0x08, 0x04, 0x04, 0x02], // '{'
    [0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04], // '|'
    [0x08, 0x04, 0x04, 0x02, 0x04, 0x04, 0x08], // '}'
    [0x00, 0x00, 0x08, 0x15, 0x02, 0x00, 0x00], // '~'
];

/// Columns of a glyph.
const GLYPH_W: i32 = 5;
/// Rows of a glyph.
const GLYPH_H: i32 = 7;
/// Advance from one glyph to the next, in font pixels (one blank column).
const ADVANCE: i32 = 6;

/// The rows of `c` ('?' for a character outside ASCII 32..=126).
pub fn glyph(c: char) -> &'static [u8; 7] {
    let code = c as u32;
    let index = if (32..=126).contains(&code) {
        code - 32
    } else {
        u32::from(b'?') - 32
    };
    &GLYPHS[index as usize]
}

/// Font pixels per glyph pixel for a font of `size` px (a 7-row glyph plus spacing ≈ 9 rows).
fn scale_for(size: f64) -> i32 {
    ((size / 9.0).round() as i32).max(1)
}

/// Width and height (px) of `text` in the bitmap font at `size`.
pub fn text_size(text: &str, size: f64) -> (u32, u32) {
    let s = scale_for(size);
    let n = text.chars().count() as i32;
    let w = if n == 0 { 0 } else { (n * ADVANCE - 1) * s };
    (w.max(0) as u32, (GLYPH_H * s) as u32)
}

/// plotters' RGB bitmap backend with text drawn by [`GLYPHS`] (see the module doc).
pub struct LabelledBitmap<'a> {
    inner: BitMapBackend<'a>,
}

impl<'a> LabelledBitmap<'a> {
    /// Draws into `buffer`, `width × height` RGB bytes.
    pub fn new(buffer: &'a mut [u8], (width, height): (u32, u32)) -> LabelledBitmap<'a> {
        LabelledBitmap {
            inner: BitMapBackend::with_buffer(buffer, (width, height)),
        }
    }
}

type BitmapError = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

impl DrawingBackend for LabelledBitmap<'_> {
    type ErrorType = BitmapError;

    fn get_size(&self) -> (u32, u32) {
        self.inner.get_size()
    }

    fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.ensure_prepared()
    }

    fn present(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.present()
    }

    fn draw_pixel(
        &mut self,
        point: BackendCoord,
        color: BackendColor,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_pixel(point, color)
    }

    fn draw_line<S: BackendStyle>(
        &mut self,
        from: BackendCoord,
        to: BackendCoord,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_line(from, to, style)
    }

    fn draw_rect<S: BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_rect(upper_left, bottom_right, style, fill)
    }

    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_path(path, style)
    }

    fn draw_circle<S: BackendStyle>(
        &mut self,
        center: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_circle(center, radius, style, fill)
    }

    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.fill_polygon(vert, style)
    }

    fn draw_text<TStyle: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &TStyle,
        pos: BackendCoord,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        let color = style.color();
        if color.alpha == 0.0 {
            return Ok(());
        }
        let scale = scale_for(style.size());
        let (width, height) = text_size(text, style.size());
        let (width, height) = (width as i32, height as i32);
        let dx = match style.anchor().h_pos {
            HPos::Left => 0,
            HPos::Right => -width,
            HPos::Center => -width / 2,
        };
        let dy = match style.anchor().v_pos {
            VPos::Top => 0,
            VPos::Center => -height / 2,
            VPos::Bottom => -height,
        };
        let transform = style.transform();
        let (w, h) = self.get_size();
        for (k, c) in text.chars().enumerate() {
            let left = k as i32 * ADVANCE * scale;
            for (row, bits) in glyph(c).iter().enumerate() {
                for col in 0..GLYPH_W {
                    if bits & (1 << (GLYPH_W - 1 - col)) == 0 {
                        continue;
                    }
                    for sy in 0..scale {
                        for sx in 0..scale {
                            let x = left + col * scale + sx + dx;
                            let y = row as i32 * scale + sy + dy;
                            let (x, y) = transform.transform(x, y);
                            let (x, y) = (pos.0 + x, pos.1 + y);
                            if x >= 0 && y >= 0 && x < w as i32 && y < h as i32 {
                                self.inner.draw_pixel((x, y), color)?;
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }

    fn estimate_text_size<TStyle: BackendTextStyle>(
        &self,
        text: &str,
        style: &TStyle,
    ) -> Result<(u32, u32), DrawingErrorKind<Self::ErrorType>> {
        Ok(text_size(text, style.size()))
    }

    fn blit_bitmap(
        &mut self,
        pos: BackendCoord,
        size: (u32, u32),
        src: &[u8],
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.blit_bitmap(pos, size, src)
    }
}

/// One chart: points (x = time, y = a metric), the indices of the Pareto front among them, and
/// a short label per point (its parameter values).
#[derive(Debug, Clone)]
pub struct ParetoChart {
    /// Caption above the plot.
    pub title: String,
    /// Axis names.
    pub x_label: String,
    /// Axis names.
    pub y_label: String,
    /// (x, y) of every point; non-finite points are left out.
    pub points: Vec<(f64, f64)>,
    /// Indices of the front's points.
    pub front: Vec<usize>,
    /// A label per point (drawn next to the front's points).
    pub labels: Vec<String>,
}

/// An axis: the data range, shown on a log₁₀ scale when it is positive and spans more than two
/// decades.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Axis {
    log: bool,
    min: f64,
    max: f64,
}

impl Axis {
    fn fit(values: impl Iterator<Item = f64> + Clone) -> Axis {
        let (lo, hi) = values
            .clone()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            });
        if !(lo.is_finite() && hi.is_finite()) {
            return Axis {
                log: false,
                min: 0.0,
                max: 1.0,
            };
        }
        let log = lo > 0.0 && hi / lo > 100.0;
        let (lo, hi) = if log {
            (lo.log10(), hi.log10())
        } else {
            (lo, hi)
        };
        let pad = if hi > lo {
            (hi - lo) * 0.06
        } else {
            lo.abs().max(1.0) * 0.1
        };
        Axis {
            log,
            min: lo - pad,
            max: hi + pad,
        }
    }

    fn map(&self, v: f64) -> f64 {
        if self.log { v.log10() } else { v }
    }

    fn label(&self, v: f64) -> String {
        let v = if self.log { 10f64.powf(v) } else { v };
        format_number(v)
    }
}

/// Compact number for axis ticks and tables: 3 significant digits, no trailing zeros.
pub fn format_number(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let a = v.abs();
    if !(1e-3..1e6).contains(&a) {
        let text = format!("{v:.2e}");
        return match text.split_once('e') {
            Some((mantissa, exponent)) if mantissa.contains('.') => format!(
                "{}e{exponent}",
                mantissa.trim_end_matches('0').trim_end_matches('.')
            ),
            _ => text,
        };
    }
    let decimals = (2 - a.log10().floor() as i32).clamp(0, 6) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

fn draw<DB: DrawingBackend>(
    area: DrawingArea<DB, plotters::coord::Shift>,
    chart: &ParetoChart,
) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    area.fill(&WHITE).map_err(err)?;
    let finite: Vec<(usize, (f64, f64))> = chart
        .points
        .iter()
        .copied()
        .enumerate()
        .filter(|(_, (x, y))| x.is_finite() && y.is_finite())
        .collect();
    let x_axis = Axis::fit(finite.iter().map(|(_, p)| p.0));
    let y_axis = Axis::fit(finite.iter().map(|(_, p)| p.1));
    let mut ctx = ChartBuilder::on(&area)
        .caption(&chart.title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(110)
        .build_cartesian_2d(x_axis.min..x_axis.max, y_axis.min..y_axis.max)
        .map_err(err)?;
    let x_name = if x_axis.log {
        format!("{} (log scale)", chart.x_label)
    } else {
        chart.x_label.clone()
    };
    let y_name = if y_axis.log {
        format!("{} (log scale)", chart.y_label)
    } else {
        chart.y_label.clone()
    };
    ctx.configure_mesh()
        .x_desc(x_name)
        .y_desc(y_name)
        .x_label_formatter(&|v| x_axis.label(*v))
        .y_label_formatter(&|v| y_axis.label(*v))
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(err)?;
    let at = |(x, y): (f64, f64)| (x_axis.map(x), y_axis.map(y));
    let grey = RGBColor(150, 150, 150);
    let others = finite
        .iter()
        .filter(|(i, _)| !chart.front.contains(i))
        .map(|(_, p)| Circle::new(at(*p), 4, grey.filled()));
    ctx.draw_series(others).map_err(err)?;
    let mut front: Vec<(usize, (f64, f64))> = finite
        .iter()
        .copied()
        .filter(|(i, _)| chart.front.contains(i))
        .collect();
    front.sort_by(|a, b| a.1.0.total_cmp(&b.1.0));
    let orange = RGBColor(230, 110, 20);
    // The front as a staircase: each point dominates everything up and to its right.
    let mut steps = Vec::new();
    for (k, (_, p)) in front.iter().enumerate() {
        if k > 0 {
            steps.push(at((p.0, front[k - 1].1.1)));
        }
        steps.push(at(*p));
    }
    ctx.draw_series(LineSeries::new(steps, Color::stroke_width(&orange, 2)))
        .map_err(err)?;
    ctx.draw_series(
        front
            .iter()
            .map(|(_, p)| Circle::new(at(*p), 6, orange.filled())),
    )
    .map_err(err)?;
    // Labels of the front's points, left out where they would overlap one already drawn.
    let label_style = ("sans-serif", 12).into_font().color(&BLACK);
    let mut taken: Vec<(i32, i32, i32, i32)> = Vec::new();
    for (i, p) in &front {
        let text = chart.labels.get(*i).cloned().unwrap_or_default();
        let (tw, th) = area.estimate_text_size(&text, &label_style).map_err(err)?;
        let (px, py) = ctx.backend_coord(&at(*p));
        let rect = (px + 8, py - 4 - th as i32, px + 8 + tw as i32, py - 4);
        let overlaps = taken
            .iter()
            .any(|t| rect.0 < t.2 && t.0 < rect.2 && rect.1 < t.3 && t.1 < rect.3);
        if !overlaps {
            area.draw(&Text::new(text, (rect.0, rect.1), label_style.clone()))
                .map_err(err)?;
            taken.push(rect);
        }
    }
    // The legend, sized by the backend's own text measure.
    let legend_style = ("sans-serif", 14).into_font().color(&BLACK);
    let entries = ["Pareto front", "other settings"];
    let mut width = 0;
    let mut line = 0;
    for e in entries {
        let (w, h) = area.estimate_text_size(e, &legend_style).map_err(err)?;
        width = width.max(w as i32);
        line = line.max(h as i32 + 8);
    }
    let (right, top) = (SIZE.0 as i32 - 30, 50);
    let left = right - width - 48;
    area.draw(&Rectangle::new(
        [(left, top), (right, top + 2 * line + 8)],
        WHITE.filled(),
    ))
    .map_err(err)?;
    area.draw(&Rectangle::new(
        [(left, top), (right, top + 2 * line + 8)],
        Color::stroke_width(&BLACK, 1),
    ))
    .map_err(err)?;
    for (k, e) in entries.iter().enumerate() {
        let y = top + 4 + k as i32 * line + line / 2;
        if k == 0 {
            area.draw(&PathElement::new(
                vec![(left + 8, y), (left + 32, y)],
                Color::stroke_width(&orange, 2),
            ))
            .map_err(err)?;
            area.draw(&Circle::new((left + 20, y), 5, orange.filled()))
                .map_err(err)?;
        } else {
            area.draw(&Circle::new((left + 20, y), 4, grey.filled()))
                .map_err(err)?;
        }
        let (_, h) = area.estimate_text_size(e, &legend_style).map_err(err)?;
        area.draw(&Text::new(
            e.to_string(),
            (left + 40, y - h as i32 / 2),
            legend_style.clone(),
        ))
        .map_err(err)?;
    }
    area.present().map_err(err)?;
    Ok(())
}

/// The chart as an SVG document.
pub fn pareto_svg(chart: &ParetoChart) -> Result<String, String> {
    let mut svg = String::new();
    {
        let area = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        draw(area, chart)?;
    }
    Ok(svg)
}

/// The chart as an RGB PNG file's bytes.
pub fn pareto_png(chart: &ParetoChart) -> Result<Vec<u8>, String> {
    let (w, h) = SIZE;
    let mut rgb = vec![255u8; (w * h * 3) as usize];
    {
        let area = LabelledBitmap::new(&mut rgb, SIZE).into_drawing_area();
        draw(area, chart)?;
    }
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, w, h);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        writer.write_image_data(&rgb).map_err(|e| e.to_string())?;
        writer.finish().map_err(|e| e.to_string())?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glyphs_are_five_columns_wide_and_distinct() {
        for g in &GLYPHS {
            assert!(g.iter().all(|row| *row < 32));
        }
        // Every printable character but the space draws something, and no two are alike.
        for (i, g) in GLYPHS.iter().enumerate().skip(1) {
            assert!(g.iter().any(|row| *row != 0), "glyph {i}");
            for (j, other) in GLYPHS.iter().enumerate().skip(i + 1) {
                assert_ne!(g, other, "glyphs {} and {}", i + 32, j + 32);
            }
        }
        assert_eq!(glyph('é'), glyph('?'));
        assert_eq!(text_size("ab", 9.0), (11, 7));
        assert_eq!(text_size("ab", 18.0), (22, 14));
    }

    #[test]
    fn numbers_are_compact() {
        assert_eq!(format_number(0.0), "0");
        assert_eq!(format_number(1.0), "1");
        assert_eq!(format_number(12.345), "12.3");
        assert_eq!(format_number(0.012345), "0.0123");
        assert_eq!(format_number(1234.6), "1235");
        assert_eq!(format_number(1e7), "1e7");
        assert_eq!(format_number(2.5e-5), "2.5e-5");
    }

    #[test]
    fn axes_switch_to_log_over_two_decades() {
        let lin = Axis::fit([1.0, 50.0].into_iter());
        assert!(!lin.log && lin.min < 1.0 && lin.max > 50.0);
        let log = Axis::fit([0.1, 1e6].into_iter());
        assert!(log.log && log.min < -1.0 && log.max > 6.0);
        assert_eq!(log.label(2.0), "100");
    }

    fn chart() -> ParetoChart {
        ParetoChart {
            title: "error vs time".into(),
            x_label: "time ms".into(),
            y_label: "error px".into(),
            points: vec![
                (1.0, 10.0),
                (2.0, 5.0),
                (3.0, 6.0),
                (4.0, 1.0),
                (f64::NAN, 1.0),
            ],
            front: vec![0, 1, 3],
            labels: vec![
                "a=1".into(),
                "a=2".into(),
                "a=3".into(),
                "a=4".into(),
                "x".into(),
            ],
        }
    }

    #[test]
    fn the_svg_holds_the_labels_and_the_front() {
        let svg = pareto_svg(&chart()).unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..40]);
        for text in [
            "error vs time",
            "time ms",
            "error px",
            "a=1",
            "a=4",
            "Pareto front",
        ] {
            assert!(svg.contains(text), "{text}");
        }
        // Only the front's points are labelled.
        assert!(!svg.contains("a=3"));
    }

    #[test]
    fn the_png_decodes_and_has_ink_in_the_front_colour() {
        let bytes = pareto_png(&chart()).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), SIZE);
        let pixels: Vec<&[u8]> = buf.chunks(3).collect();
        let orange = pixels
            .iter()
            .filter(|p| p[0] > 200 && p[1] > 90 && p[1] < 130 && p[2] < 40)
            .count();
        let dark = pixels
            .iter()
            .filter(|p| p[0] < 60 && p[1] < 60 && p[2] < 60)
            .count();
        assert!(orange > 200, "{orange} front pixels");
        // Text and axes in black.
        assert!(dark > 2000, "{dark} dark pixels");
    }
}
