//! Details for [`Predictor::Axes`] stores: after the level walks have settled ownership, subtree
//! bounds and empty children (none of which depend on the predictor), every new vertex's detail
//! is computed again against the axes prediction, in the order synthesis will run it (closed
//! loop, as for the parent predictor).
//!
//! [`Predictor::Axes`]: tetwave_protocol::wavelet::Predictor::Axes

use super::walk::Owner;
use super::walk::{load, store, Cell};
use super::AnalysisError;
use std::sync::atomic::AtomicU32;
use tetwave_protocol::axes::Grid;
use tetwave_protocol::wavelet::{analyze, synthesize, LevelSteps, Quantizer};
use tetwave_protocol::{BaseMesh, VertexKeys};

/// Largest sample magnitude the axes predictor takes: its cubic sums 18 times a value, which
/// must stay a finite f32 (`prepare --predictor auto` takes the parent predictor above it).
pub const AXES_MAX_MAGNITUDE: f32 = 1e36;

/// Replaces `detail` and the reconstructions in `cells` with the axes predictor's; returns the
/// max |synthesis − sample|.
pub(super) fn details<O: Owner>(
    base: &BaseMesh,
    keys: &VertexKeys,
    reference: &[AtomicU32],
    cells: &[Cell<O>],
    detail: &[AtomicU32],
    quantizer: Option<(Quantizer, LevelSteps)>,
) -> Result<f64, AnalysisError> {
    let grid = Grid::of(base, keys)?;
    let mut rec: Vec<f32> = cells.iter().map(|c| load(&c.rec)).collect();
    let mut err = 0f64;
    let levels = quantizer.map(|(q, steps)| steps.quantizers(q, base.levels));
    grid.predict_all(&mut rec, |k, p, above| {
        let f = load(&reference[k]);
        let d = match &levels {
            None => analyze(f, p),
            Some(qs) => {
                let q = qs[above as usize];
                q.decode(q.encode(f - p))
            }
        };
        let x = synthesize(d, p);
        store(&detail[k], d);
        store(&cells[k].rec, x);
        err = if x.is_finite() && d.is_finite() {
            err.max((x as f64 - f as f64).abs())
        } else {
            f64::INFINITY
        };
        x
    });
    if err.is_infinite() {
        // (samples within AXES_MAX_MAGNITUDE keep every prediction finite; this is a backstop)
        return Err(AnalysisError::AxesOverflow(f64::INFINITY));
    }
    Ok(err)
}
