//! `Series`: a real-time node's per-cycle series, streamed to a file, its percentiles from 1 µs bins.

use std::path::PathBuf;

use super::*;
use crate::series::Series as CoreSeries;

/// A node's (t, value) rows (engine/src/series.rs): streamed to ``path`` (or kept, without one), counted in 1 µs bins.
#[pyclass(module = "trainhil_engine._native")]
pub struct Series {
    inner: CoreSeries,
    path: Option<PathBuf>,
}

#[pymethods]
impl Series {
    /// `path`: the file the rows are appended to (created 0600); None: the rows stay in memory.
    #[new]
    #[pyo3(signature = (path = None))]
    fn new(path: Option<PathBuf>) -> PyResult<Self> {
        Ok(Series { inner: CoreSeries::open(path.as_deref())?, path })
    }

    /// One row (t, value); a non-finite value is recorded but not counted.
    fn add(&mut self, t: f64, value: f64) -> PyResult<()> {
        Ok(self.inner.add(t, value)?)
    }

    /// Rows [(t, value)] in order, as `add` each.
    fn extend(&mut self, rows: Vec<(f64, f64)>) -> PyResult<()> {
        for (t, value) in rows {
            self.inner.add(t, value)?;
        }
        Ok(())
    }

    /// Write the rows not written yet.
    fn flush(&mut self) -> PyResult<()> {
        Ok(self.inner.flush()?)
    }

    /// Flush and close the file.
    fn close(&mut self) -> PyResult<()> {
        Ok(self.inner.close()?)
    }

    /// As `np.percentile(values, q)` over the values rounded to the microsecond; None without values.
    fn percentile(&self, q: f64) -> Option<f64> {
        self.inner.percentile(q)
    }

    /// The rows not written yet (all of them without a file), t and value interleaved, native float64.
    fn pending_bytes<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        PyBytes::new(py, &self.inner.pending_bytes())
    }

    /// The file the rows go to (None: kept in memory).
    #[getter]
    fn path(&self) -> Option<PathBuf> {
        self.path.clone()
    }

    /// How many finite values were added.
    #[getter]
    fn n(&self) -> u64 {
        self.inner.n
    }

    /// The largest finite value (-inf before any).
    #[getter]
    fn max(&self) -> f64 {
        self.inner.max
    }
}
