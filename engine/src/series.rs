//! A real-time node's per-cycle series (ECU cycle lateness, plant publication lateness, sensor-to-actuator
//! latency): (t, value) rows streamed to a file as they come, the distribution kept in 1 µs bins.
//!
//! The rows go to the file as native float64 pairs, appended every `FLUSH_ROWS` rows and at `flush`, so a node's
//! memory does not grow with the run; a file is opened for appending, so a restarted node's rows follow its
//! predecessor's. Percentiles are numpy's linear interpolation over the values rounded to the microsecond; the
//! maximum and the count (of finite values) are exact. Without a file the rows stay in memory.

use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;

pub const RESOLUTION_S: f64 = 1e-6;
pub const FLUSH_ROWS: usize = 1024;

/// (t, value) rows, streamed to a file (or kept, without one), their values counted in 1 µs bins.
#[derive(Debug, Default)]
pub struct Series {
    file: Option<File>,
    /// t, value, t, value, ... not yet written (all of them without a file).
    rows: Vec<f64>,
    /// value in µs -> count
    bins: BTreeMap<i64, u64>,
    /// Finite values added.
    pub n: u64,
    /// The largest finite value (-inf before any).
    pub max: f64,
}

impl Series {
    /// A series streamed to `path` (created with mode 0600 if absent, appended to), or kept in memory (None).
    pub fn open(path: Option<&Path>) -> io::Result<Series> {
        let file = match path {
            Some(p) => Some(OpenOptions::new().append(true).create(true).mode(0o600).open(p)?),
            None => None,
        };
        Ok(Series { file, rows: Vec::new(), bins: BTreeMap::new(), n: 0, max: f64::NEG_INFINITY })
    }

    /// One row; a non-finite value is recorded but has no place in the distribution.
    pub fn add(&mut self, t: f64, value: f64) -> io::Result<()> {
        self.rows.push(t);
        self.rows.push(value);
        if self.file.is_some() && self.rows.len() >= 2 * FLUSH_ROWS {
            self.flush()?;
        }
        if value.is_finite() {
            *self.bins.entry((value / RESOLUTION_S).round_ties_even() as i64).or_insert(0) += 1;
            self.n += 1;
            if value > self.max {
                self.max = value;
            }
        }
        Ok(())
    }

    /// Write the rows not written yet (nothing without a file).
    pub fn flush(&mut self) -> io::Result<()> {
        if let Some(file) = self.file.as_mut() {
            if !self.rows.is_empty() {
                file.write_all(&pending_bytes(&self.rows))?;
                self.rows.clear();
            }
        }
        Ok(())
    }

    /// Flush and close the file; rows added later stay in memory.
    pub fn close(&mut self) -> io::Result<()> {
        self.flush()?;
        self.file = None;
        Ok(())
    }

    /// The rows not written yet, t and value interleaved.
    pub fn pending(&self) -> &[f64] {
        &self.rows
    }

    /// The rows not written yet as the file holds them: native float64, t and value interleaved.
    pub fn pending_bytes(&self) -> Vec<u8> {
        pending_bytes(&self.rows)
    }

    /// As `np.percentile(values, q)` over the finite values rounded to the microsecond; None without values.
    pub fn percentile(&self, q: f64) -> Option<f64> {
        if self.n == 0 {
            return None;
        }
        let pos = q / 100.0 * (self.n - 1) as f64;
        let (lo, hi) = (pos.floor() as u64, pos.ceil() as u64);
        let (a, b) = (self.value_at_rank(lo), self.value_at_rank(hi));
        Some(a + (b - a) * (pos - lo as f64))
    }

    /// The value of rank `k` (0-based) in ascending order: the first bin whose cumulative count exceeds it.
    fn value_at_rank(&self, k: u64) -> f64 {
        let mut cum = 0;
        for (&key, &count) in &self.bins {
            cum += count;
            if cum > k {
                return key as f64 * RESOLUTION_S;
            }
        }
        self.bins.keys().next_back().map_or(f64::NAN, |&key| key as f64 * RESOLUTION_S)
    }
}

/// Floats as native float64 bytes (the series file's format).
fn pending_bytes(rows: &[f64]) -> Vec<u8> {
    rows.iter().flat_map(|x| x.to_ne_bytes()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// numpy's default percentile (linear) over sorted values.
    fn linear_percentile(sorted: &[f64], q: f64) -> f64 {
        let pos = q / 100.0 * (sorted.len() - 1) as f64;
        let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
        sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
    }

    #[test]
    fn percentiles_are_the_linear_ones_of_the_values_rounded_to_the_microsecond() {
        let mut s = Series::open(None).unwrap();
        let values: Vec<f64> = (0..1001).map(|k| ((k * 7919) % 1001) as f64 * 1.3e-6).collect();
        for &v in &values {
            s.add(0.0, v).unwrap();
        }
        let mut rounded: Vec<f64> = values.iter().map(|v| (v / RESOLUTION_S).round_ties_even() * RESOLUTION_S).collect();
        rounded.sort_by(f64::total_cmp);
        for q in [0.0, 50.0, 99.0, 99.9, 100.0] {
            assert!((s.percentile(q).unwrap() - linear_percentile(&rounded, q)).abs() < 1e-12, "q = {q}");
        }
        assert_eq!(s.n, 1001);
        assert_eq!(s.max, 1000.0 * 1.3e-6);
    }

    #[test]
    fn a_non_finite_value_is_a_row_but_not_in_the_distribution() {
        let mut s = Series::open(None).unwrap();
        s.add(1.0, f64::NAN).unwrap();
        assert_eq!(s.percentile(50.0), None);
        s.add(2.0, 3e-6).unwrap();
        assert_eq!((s.n, s.percentile(50.0)), (1, Some(3e-6)));
        assert_eq!(s.pending().len(), 4);
    }

    #[test]
    fn rows_are_appended_to_the_file_every_flush_rows_and_at_close() {
        let dir = std::env::temp_dir().join(format!("series_test_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("s.bin");
        let _ = std::fs::remove_file(&path);
        for round in 0..2 {
            let mut s = Series::open(Some(&path)).unwrap();
            for k in 0..FLUSH_ROWS + 3 {
                s.add(k as f64, round as f64).unwrap();
            }
            assert_eq!(s.pending().len(), 6); // the first FLUSH_ROWS are on disk
            s.close().unwrap();
        }
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes.len(), 2 * (FLUSH_ROWS + 3) * 16); // the second series followed the first
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
