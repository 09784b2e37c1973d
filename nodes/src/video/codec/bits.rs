//! Bit-level writer and reader with Exp-Golomb codes (order 0), MSB first.
//!
//! `ue(v)`: `v + 1` written in binary (`n + 1` bits) after `n` zero bits, where `n` is the
//! number of bits of `v + 1` minus one (H.264 §9.1). The reader refuses codes with more than
//! [`MAX_LEADING_ZEROS`] leading zeros and reads past the end as an error, never a panic.

/// Longest run of leading zeros accepted in an Exp-Golomb code (values up to 2³² − 2).
pub const MAX_LEADING_ZEROS: u32 = 31;

/// Appends bits MSB first to a byte vector.
#[derive(Debug, Default, Clone)]
pub struct BitWriter {
    bytes: Vec<u8>,
    /// Pending bits, right-aligned.
    acc: u64,
    /// Number of pending bits in `acc` (< 8 between calls).
    pending: u32,
}

impl BitWriter {
    /// An empty writer.
    pub fn new() -> BitWriter {
        BitWriter::default()
    }

    /// Bits written so far.
    pub fn bit_len(&self) -> u64 {
        self.bytes.len() as u64 * 8 + u64::from(self.pending)
    }

    /// Writes the low `n` bits of `value` (n ≤ 32), MSB first.
    pub fn put_bits(&mut self, value: u32, n: u32) {
        debug_assert!(n <= 32);
        if n == 0 {
            return;
        }
        let masked = u64::from(value) & ((1u64 << n) - 1);
        self.acc = (self.acc << n) | masked;
        self.pending += n;
        while self.pending >= 8 {
            self.pending -= 8;
            self.bytes.push((self.acc >> self.pending) as u8);
        }
        self.acc &= (1u64 << self.pending) - 1;
    }

    /// Writes one bit.
    pub fn put_bit(&mut self, bit: bool) {
        self.put_bits(u32::from(bit), 1);
    }

    /// Writes `v` as an unsigned Exp-Golomb code; values above 2³² − 2 are written as
    /// 2³² − 2 (callers keep their values far below).
    pub fn put_ue(&mut self, v: u32) {
        let x = u64::from(v.min(u32::MAX - 1)) + 1;
        let len = 64 - x.leading_zeros(); // bits of v + 1, ≤ 32
        self.put_bits(0, len - 1);
        self.put_bits(x as u32, len);
    }

    /// Writes `v` as a signed Exp-Golomb code (0, 1, −1, 2, −2, … → 0, 1, 2, 3, 4, …);
    /// `i32::MIN` is written as `−(2³¹ − 1)`.
    pub fn put_se(&mut self, v: i32) {
        let mapped = if v > 0 {
            2 * u64::from(v.unsigned_abs()) - 1
        } else {
            2 * u64::from(v.unsigned_abs())
        };
        self.put_ue(mapped.min(u64::from(u32::MAX - 1)) as u32);
    }

    /// Pads the last byte with zero bits and returns the bytes.
    pub fn finish(mut self) -> Vec<u8> {
        if self.pending > 0 {
            let pad = 8 - self.pending;
            self.put_bits(0, pad);
        }
        self.bytes
    }
}

/// Reads bits MSB first from a byte slice.
#[derive(Debug, Clone)]
pub struct BitReader<'a> {
    bytes: &'a [u8],
    /// Position in bits.
    pos: u64,
}

/// The error of reading past the end of the stream.
pub const TRUNCATED: &str = "the bitstream is truncated (read past its end)";

impl<'a> BitReader<'a> {
    /// A reader at the first bit of `bytes`.
    pub fn new(bytes: &'a [u8]) -> BitReader<'a> {
        BitReader { bytes, pos: 0 }
    }

    /// Bits read so far.
    pub fn position(&self) -> u64 {
        self.pos
    }

    /// Bits left.
    pub fn remaining(&self) -> u64 {
        (self.bytes.len() as u64 * 8).saturating_sub(self.pos)
    }

    /// Reads one bit.
    pub fn bit(&mut self) -> Result<bool, String> {
        let byte = self
            .bytes
            .get((self.pos / 8) as usize)
            .ok_or_else(|| TRUNCATED.to_string())?;
        let b = (byte >> (7 - (self.pos % 8))) & 1;
        self.pos += 1;
        Ok(b == 1)
    }

    /// Reads `n ≤ 32` bits as an unsigned number, MSB first.
    pub fn bits(&mut self, n: u32) -> Result<u32, String> {
        debug_assert!(n <= 32);
        if u64::from(n) > self.remaining() {
            return Err(TRUNCATED.into());
        }
        let mut v = 0u64;
        for _ in 0..n {
            v = (v << 1) | u64::from(self.bit()?);
        }
        Ok(v as u32)
    }

    /// Reads an unsigned Exp-Golomb code.
    pub fn ue(&mut self) -> Result<u32, String> {
        let mut zeros = 0u32;
        while !self.bit()? {
            zeros += 1;
            if zeros > MAX_LEADING_ZEROS {
                return Err(format!(
                    "corrupt bitstream: an Exp-Golomb code at bit {} has more than \
                     {MAX_LEADING_ZEROS} leading zeros",
                    self.pos
                ));
            }
        }
        let rest = self.bits(zeros)?;
        Ok((((1u64 << zeros) | u64::from(rest)) - 1) as u32)
    }

    /// Reads a signed Exp-Golomb code.
    pub fn se(&mut self) -> Result<i32, String> {
        let k = i64::from(self.ue()?);
        let v = if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) };
        Ok(v as i32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn exp_golomb_codewords_match_the_standard_table() {
        // H.264 Table 9-2: 0 → 1, 1 → 010, 2 → 011, 3 → 00100, 7 → 0001000.
        let mut w = BitWriter::new();
        for v in [0, 1, 2, 3, 7] {
            w.put_ue(v);
        }
        assert_eq!(w.bit_len(), 1 + 3 + 3 + 5 + 7);
        let bytes = w.finish();
        // 1 010 011 00100 0001000 + pad: 1010_0110 0100_0001 0000_0000
        assert_eq!(bytes, vec![0b1010_0110, 0b0100_0001, 0b0000_0000]);
    }

    #[test]
    fn reading_past_the_end_is_an_error() {
        let mut r = BitReader::new(&[0b0000_0000]);
        assert!(r.ue().is_err());
        let mut r = BitReader::new(&[]);
        assert!(r.bit().is_err());
        let zeros = [0u8; 8];
        let mut r = BitReader::new(&zeros);
        assert!(r.ue().unwrap_err().contains("leading zeros"));
    }

    proptest! {
        #[test]
        fn values_round_trip(values in proptest::collection::vec((any::<u32>(), any::<i32>(), 0u32..=32), 0..64)) {
            let mut w = BitWriter::new();
            for &(u, s, n) in &values {
                let u = u.min(u32::MAX - 1);
                let s = s.max(-(i32::MAX));
                w.put_ue(u);
                w.put_se(s);
                let mask = if n == 32 { u32::MAX } else { (1u32 << n) - 1 };
                w.put_bits(u & mask, n);
            }
            let bytes = w.finish();
            let mut r = BitReader::new(&bytes);
            for &(u, s, n) in &values {
                let u = u.min(u32::MAX - 1);
                let s = s.max(-(i32::MAX));
                prop_assert_eq!(r.ue().unwrap(), u);
                prop_assert_eq!(r.se().unwrap(), s);
                let mask = if n == 32 { u32::MAX } else { (1u32 << n) - 1 };
                prop_assert_eq!(r.bits(n).unwrap(), u & mask);
            }
            prop_assert!(r.remaining() < 8);
        }
    }
}
