//! Border handling: where a filter reads when its window reaches past the edge of the image.
//!
//! The five modes are OpenCV's border types (`cv::BorderTypes`). Illustrated on a row `abcdefgh`,
//! with the extension on both sides:
//!
//! | mode          | OpenCV               | extended row                |
//! |---------------|----------------------|-----------------------------|
//! | `constant`    | `BORDER_CONSTANT`    | `iiiiii|abcdefgh|iiiiiii`   |
//! | `wrap`        | `BORDER_WRAP`        | `cdefgh|abcdefgh|abcdefg`   |
//! | `reflect`     | `BORDER_REFLECT`     | `fedcba|abcdefgh|hgfedcb`   |
//! | `reflect_101` | `BORDER_REFLECT_101` | `gfedcb|abcdefgh|gfedcba`   |
//! | `clamp`       | `BORDER_REPLICATE`   | `aaaaaa|abcdefgh|hhhhhhh`   |
//!
//! [`map_index`] is the one rule, valid for any offset (a window wider than the image reflects
//! back and forth as often as needed, like OpenCV's `borderInterpolate`). [`BorderTable`]
//! precomputes it for one line with a given reach before and after, and pads rows into scratch
//! buffers, so a filter's inner loop runs over contiguous memory without a branch per pixel.

use ocellus_engine::param_enum;

param_enum! {
    /// How pixels outside the image are read (OpenCV's border types).
    pub enum BorderMode {
        /// A fixed value (the operator's `border_value`): `iii|abcdefgh|iii` (`BORDER_CONSTANT`).
        Constant = "constant",
        /// Periodic: `fgh|abcdefgh|abc` (`BORDER_WRAP`).
        Wrap = "wrap",
        /// Mirror, repeating the edge pixel: `cba|abcdefgh|hgf` (`BORDER_REFLECT`).
        Reflect = "reflect",
        /// Mirror about the edge pixel: `dcb|abcdefgh|gfe` (`BORDER_REFLECT_101`, the default).
        Reflect101 = "reflect_101",
        /// Repeat the edge pixel: `aaa|abcdefgh|hhh` (`BORDER_REPLICATE`).
        Clamp = "clamp",
    }
}

impl Default for BorderMode {
    /// `reflect_101`, OpenCV's default border for filtering.
    fn default() -> Self {
        BorderMode::Reflect101
    }
}

/// Checks a filter's `border_value` parameter: it must be finite, and it may differ from its
/// default 0 only with the constant border (any other border would ignore it).
pub fn check_border_value(border: BorderMode, border_value: f64) -> Result<(), String> {
    if !border_value.is_finite() {
        return Err(format!("`border_value` must be finite, got {border_value}"));
    }
    if border != BorderMode::Constant && border_value != 0.0 {
        return Err(format!(
            "`border_value` applies only to border \"constant\" (border is \"{}\")",
            border.name()
        ));
    }
    Ok(())
}

/// The index inside `0..len` that position `i` of a line of `len` samples reads under `mode`,
/// or `None` when it reads the constant border value (mode `constant` outside the line, or an
/// empty line).
///
/// Inside the line (`0 ≤ i < len`) the result is `i` for every mode. Outside, any offset is
/// allowed: the mirror modes fold back and forth as often as needed, `wrap` is `i mod len`, and
/// `reflect_101` on a one-sample line always reads sample 0 (as OpenCV's `borderInterpolate`).
pub fn map_index(i: isize, len: usize, mode: BorderMode) -> Option<usize> {
    if len == 0 {
        return None;
    }
    if let Ok(inside) = usize::try_from(i)
        && inside < len
    {
        return Some(inside);
    }
    // Wide integers keep `2 · len` and the remainders exact for every `isize` and `usize`.
    let i = i as i128;
    let n = len as i128;
    let mapped = match mode {
        BorderMode::Constant => return None,
        BorderMode::Clamp => i.clamp(0, n - 1),
        BorderMode::Wrap => i.rem_euclid(n),
        BorderMode::Reflect => {
            let period = 2 * n;
            let m = i.rem_euclid(period);
            if m < n { m } else { period - 1 - m }
        }
        BorderMode::Reflect101 => {
            if n == 1 {
                0
            } else {
                let period = 2 * (n - 1);
                let m = i.rem_euclid(period);
                if m < n { m } else { period - m }
            }
        }
    };
    usize::try_from(mapped).ok()
}

/// The border mapping of one line (a row or a column) of `len` samples, extended by `before`
/// positions on the left (top) and `after` on the right (bottom).
///
/// Positions are counted in the extended line: position `k` stands for index `k − before` of the
/// original line, so a filter window of `before + 1 + after` taps centred on sample `x` covers
/// positions `x .. x + before + after`. A separable filter builds one table for the columns and
/// one for the rows and reuses them for every line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BorderTable {
    len: usize,
    before: usize,
    after: usize,
    mode: BorderMode,
    /// Sources of positions `0..before`.
    left: Vec<Option<usize>>,
    /// Sources of positions `before + len .. before + len + after`.
    right: Vec<Option<usize>>,
}

impl BorderTable {
    /// The table for a line of `len` samples with `before` extra positions before it and `after`
    /// after it.
    pub fn new(len: usize, before: usize, after: usize, mode: BorderMode) -> BorderTable {
        let left = (0..before)
            .map(|k| map_index(0isize.saturating_sub_unsigned(before - k), len, mode))
            .collect();
        let right = (0..after)
            .map(|k| {
                let i = isize::try_from(len.saturating_add(k)).unwrap_or(isize::MAX);
                map_index(i, len, mode)
            })
            .collect();
        BorderTable {
            len,
            before,
            after,
            mode,
            left,
            right,
        }
    }

    /// The table for a window of radius `radius` (`2·radius + 1` taps, centred).
    pub fn symmetric(len: usize, radius: usize, mode: BorderMode) -> BorderTable {
        BorderTable::new(len, radius, radius, mode)
    }

    /// Samples in the original line.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when the original line is empty (every position reads the constant).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Extra positions before the line.
    pub fn before(&self) -> usize {
        self.before
    }

    /// Extra positions after the line.
    pub fn after(&self) -> usize {
        self.after
    }

    /// The border mode.
    pub fn mode(&self) -> BorderMode {
        self.mode
    }

    /// Positions in the extended line: `before + len + after`.
    pub fn padded_len(&self) -> usize {
        self.before + self.len + self.after
    }

    /// The original index that extended position `k` reads, `None` for the constant value (or
    /// for `k` past the extended line).
    pub fn source(&self, k: usize) -> Option<usize> {
        if k < self.before {
            return self.left.get(k).copied().flatten();
        }
        let inside = k - self.before;
        if inside < self.len {
            return Some(inside);
        }
        self.right.get(inside - self.len).copied().flatten()
    }

    /// The source of every extended position, in order (`padded_len` items).
    pub fn indices(&self) -> impl Iterator<Item = Option<usize>> + '_ {
        self.left
            .iter()
            .copied()
            .chain((0..self.len).map(Some))
            .chain(self.right.iter().copied())
    }

    /// Writes the extended copy of `row` into `padded`: `row` holds `len` pixels of `channels`
    /// interleaved samples, `padded` receives `padded_len` pixels; positions reading the constant
    /// get `constant` in every channel.
    ///
    /// Slices of other lengths are not an error: only the pixels that fit both are written.
    pub fn pad_row<T: Copy>(&self, row: &[T], channels: usize, constant: T, padded: &mut [T]) {
        self.pad_row_with(row, channels, constant, padded, |x| x);
    }

    /// [`pad_row`](Self::pad_row) converting each sample with `convert` on the way (e.g. u8 to
    /// the f32 or fixed-point type a filter accumulates in), in one pass over the row.
    pub fn pad_row_with<T: Copy, U: Copy>(
        &self,
        row: &[T],
        channels: usize,
        constant: U,
        padded: &mut [U],
        convert: impl Fn(T) -> U,
    ) {
        self.pad_range_with(row, channels, 0, constant, padded, convert);
    }

    /// Like [`pad_row_with`](Self::pad_row_with) for part of the extended line only: `padded`
    /// receives the pixels of extended positions `start .. start + padded.len() / channels`.
    /// Filters that work in vertical strips (to keep their buffers in cache) pad each strip
    /// with its halo this way.
    pub fn pad_range_with<T: Copy, U: Copy>(
        &self,
        row: &[T],
        channels: usize,
        start: usize,
        constant: U,
        padded: &mut [U],
        convert: impl Fn(T) -> U,
    ) {
        if channels == 0 {
            return;
        }
        let fill = |dst: &mut [U], source: Option<usize>| {
            let pixel = source.and_then(|s| row.get(s * channels..(s + 1) * channels));
            match pixel {
                Some(pixel) => {
                    for (d, &x) in dst.iter_mut().zip(pixel) {
                        *d = convert(x);
                    }
                }
                None => dst.fill(constant),
            }
        };
        let end = start + padded.len() / channels;
        let inside_start = self.before.clamp(start, end);
        let inside_end = (self.before + self.len).clamp(start, end);
        let (left, rest) = padded.split_at_mut((inside_start - start) * channels);
        let (middle, right) = rest.split_at_mut((inside_end - inside_start) * channels);
        for (dst, k) in left.chunks_exact_mut(channels).zip(start..) {
            fill(dst, self.left.get(k).copied().flatten());
        }
        let from = inside_start.saturating_sub(self.before) * channels;
        if let Some(inside) = row.get(from..) {
            for (d, &x) in middle.iter_mut().zip(inside) {
                *d = convert(x);
            }
        }
        for (dst, k) in right.chunks_exact_mut(channels).zip(inside_end..) {
            let source = self.right.get(k - (self.before + self.len));
            fill(dst, source.copied().flatten());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn row(len: usize, mode: BorderMode) -> Vec<Option<usize>> {
        (-3..len as isize + 3)
            .map(|i| map_index(i, len, mode))
            .collect()
    }

    /// Parses a table written as digits, `-` for the constant.
    fn table(text: &str) -> Vec<Option<usize>> {
        text.chars()
            .filter(|c| !c.is_whitespace() && *c != '|')
            .map(|c| c.to_digit(10).map(|d| d as usize))
            .collect()
    }

    #[test]
    fn tables_for_length_1() {
        use BorderMode::*;
        assert_eq!(row(1, Constant), table("--- | 0 | ---"));
        assert_eq!(row(1, Wrap), table("000 | 0 | 000"));
        assert_eq!(row(1, Reflect), table("000 | 0 | 000"));
        assert_eq!(row(1, Reflect101), table("000 | 0 | 000"));
        assert_eq!(row(1, Clamp), table("000 | 0 | 000"));
    }

    #[test]
    fn tables_for_length_2() {
        use BorderMode::*;
        assert_eq!(row(2, Constant), table("--- | 01 | ---"));
        assert_eq!(row(2, Wrap), table("101 | 01 | 010"));
        assert_eq!(row(2, Reflect), table("110 | 01 | 100"));
        assert_eq!(row(2, Reflect101), table("101 | 01 | 010"));
        assert_eq!(row(2, Clamp), table("000 | 01 | 111"));
    }

    #[test]
    fn tables_for_length_5() {
        use BorderMode::*;
        assert_eq!(row(5, Constant), table("--- | 01234 | ---"));
        assert_eq!(row(5, Wrap), table("234 | 01234 | 012"));
        assert_eq!(row(5, Reflect), table("210 | 01234 | 432"));
        assert_eq!(row(5, Reflect101), table("321 | 01234 | 321"));
        assert_eq!(row(5, Clamp), table("000 | 01234 | 444"));
    }

    #[test]
    fn far_offsets_fold_back_and_forth() {
        // Period 2·len for reflect, 2·(len − 1) for reflect_101.
        let reflect: Vec<_> = (-8..0)
            .map(|i| map_index(i, 3, BorderMode::Reflect))
            .collect();
        assert_eq!(reflect, table("10012210"));
        let r101: Vec<_> = (5..13)
            .map(|i| map_index(i, 3, BorderMode::Reflect101))
            .collect();
        assert_eq!(r101, table("12101210"));
        assert_eq!(map_index(isize::MIN, 7, BorderMode::Clamp), Some(0));
        assert_eq!(map_index(isize::MAX, 7, BorderMode::Clamp), Some(6));
    }

    #[test]
    fn empty_line_reads_the_constant() {
        for &mode in BorderMode::ALL {
            assert_eq!(map_index(0, 0, mode), None);
            assert_eq!(map_index(-1, 0, mode), None);
            let t = BorderTable::symmetric(0, 2, mode);
            assert!(t.indices().all(|s| s.is_none()));
        }
    }

    #[test]
    fn default_is_reflect_101() {
        assert_eq!(BorderMode::default(), BorderMode::Reflect101);
        assert_eq!(BorderMode::Reflect101.name(), "reflect_101");
    }

    #[test]
    fn pads_interleaved_rows() {
        // Two-channel pixels (10, 11), (20, 21), (30, 31).
        let src = [10u8, 11, 20, 21, 30, 31];
        let t = BorderTable::new(3, 2, 1, BorderMode::Reflect101);
        let mut out = [0u8; 12];
        t.pad_row(&src, 2, 99, &mut out);
        assert_eq!(out, [30, 31, 20, 21, 10, 11, 20, 21, 30, 31, 20, 21]);
        let t = BorderTable::new(3, 1, 2, BorderMode::Constant);
        t.pad_row(&src, 2, 99, &mut out);
        assert_eq!(out, [99, 99, 10, 11, 20, 21, 30, 31, 99, 99, 99, 99]);
        let mut wide = [0u16; 12];
        t.pad_row_with(&src, 2, 7, &mut wide, |x| u16::from(x) << 8);
        assert_eq!(wide[..4], [7, 7, 2560, 2816]);
        assert_eq!(wide[8..], [7, 7, 7, 7]);
    }

    #[test]
    fn table_wider_than_the_line() {
        let t = BorderTable::symmetric(2, 5, BorderMode::Reflect);
        let got: Vec<_> = t.indices().collect();
        assert_eq!(got, table("00110 | 01 | 10011"));
        assert_eq!(t.padded_len(), 12);
        assert_eq!(t.source(12), None);
    }

    fn any_mode() -> impl Strategy<Value = BorderMode> {
        prop::sample::select(BorderMode::ALL.to_vec())
    }

    proptest! {
        #[test]
        fn result_in_range(i in any::<isize>(), len in 0usize..1000, mode in any_mode()) {
            if let Some(j) = map_index(i, len, mode) {
                prop_assert!(j < len);
            }
        }

        #[test]
        fn identity_inside(len in 1usize..10_000, frac in 0.0f64..1.0, mode in any_mode()) {
            let i = ((len as f64 * frac) as usize).min(len - 1);
            prop_assert_eq!(map_index(i as isize, len, mode), Some(i));
        }

        #[test]
        fn only_constant_reads_nothing(i in -100_000isize..100_000, len in 1usize..50, mode in any_mode()) {
            let inside = (0..len as isize).contains(&i);
            let got = map_index(i, len, mode);
            prop_assert_eq!(got.is_none(), mode == BorderMode::Constant && !inside);
        }

        #[test]
        fn wrap_is_modular(i in any::<isize>(), len in 1usize..100_000) {
            let expected = (i as i128).rem_euclid(len as i128) as usize;
            prop_assert_eq!(map_index(i, len, BorderMode::Wrap), Some(expected));
        }

        #[test]
        fn reflections_are_periodic_and_mirrored(i in -10_000isize..10_000, len in 1usize..200) {
            let n = len as isize;
            let r = |i| map_index(i, len, BorderMode::Reflect);
            let r101 = |i| map_index(i, len, BorderMode::Reflect101);
            // Reflect mirrors about −½: position −1 − i reads what i reads.
            prop_assert_eq!(r(-1 - i), r(i));
            prop_assert_eq!(r(i + 2 * n), r(i));
            // Reflect_101 mirrors about 0.
            prop_assert_eq!(r101(-i), r101(i));
            if len > 1 {
                prop_assert_eq!(r101(i + 2 * (n - 1)), r101(i));
            } else {
                prop_assert_eq!(r101(i), Some(0));
            }
        }

        #[test]
        fn clamp_is_nearest_edge(i in any::<isize>(), len in 1usize..1000) {
            let expected = if i < 0 { 0 } else { (i as usize).min(len - 1) };
            prop_assert_eq!(map_index(i, len, BorderMode::Clamp), Some(expected));
        }

        #[test]
        fn ranges_pad_like_whole_rows(
            len in 0usize..12,
            before in 0usize..9,
            after in 0usize..9,
            channels in 1usize..4,
            range in (0usize..40, 0usize..40),
            mode in any_mode(),
        ) {
            let t = BorderTable::new(len, before, after, mode);
            let row: Vec<u16> = (0..len * channels).map(|i| i as u16 + 1).collect();
            let mut whole = vec![0u32; t.padded_len() * channels];
            t.pad_row_with(&row, channels, 99, &mut whole, u32::from);
            let start = range.0.min(t.padded_len());
            let end = (start + range.1).min(t.padded_len());
            let mut part = vec![0u32; (end - start) * channels];
            t.pad_range_with(&row, channels, start, 99, &mut part, u32::from);
            prop_assert_eq!(&part[..], &whole[start * channels..end * channels]);
        }

        #[test]
        fn table_matches_map_index(len in 0usize..20, before in 0usize..40, after in 0usize..40, mode in any_mode()) {
            let t = BorderTable::new(len, before, after, mode);
            let got: Vec<_> = t.indices().collect();
            prop_assert_eq!(got.len(), t.padded_len());
            for (k, s) in got.iter().enumerate() {
                prop_assert_eq!(*s, map_index(k as isize - before as isize, len, mode));
                prop_assert_eq!(*s, t.source(k));
            }
        }
    }
}
