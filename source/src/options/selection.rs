//! The selection options `tetwave stream`, `tetwave view` and `tetwave-bench progressive` share:
//! which criterion decides a split, the image criterion's threshold, and the leaf budget.

use serde::Serialize;
use tetwave_adaptive::select::SelectParams;
use tetwave_protocol::view::DEFAULT_IMAGE_EPS;
use tetwave_protocol::BaseMesh;
use tetwave_render::transfer::TransferFunction;

/// What decides whether a node is refined.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Criterion {
    /// Screen-space error × how much of a pixel's colour the node's subtree can still change
    /// under the transfer function (a subtree with nothing to change is never refined).
    Image,
    /// Screen-space error alone (the thesis'): every node larger than the tolerance is refined.
    Geometric,
}

/// Client bytes per leaf the default leaf budget allows for: the mesh's 51 B a leaf tet and the
/// selector's caches, measured by `tetwave-bench progressive` (B/leaf (+sel) columns), rounded up
/// with room for the detail buffer.
pub const BYTES_PER_LEAF: u64 = 200;

#[derive(Debug, Clone, clap::Args)]
pub struct SelectionArgs {
    /// What decides a split: `image` (the screen-space error weighted by how much the node's
    /// subtree can still change the image under the transfer function) or `geometric` (the
    /// screen-space error alone).
    #[arg(long, value_enum, default_value_t = Criterion::Image)]
    pub criterion: Criterion,
    /// With `--criterion image`: the worst-case colour change of one ray segment (0–1) that
    /// counts as a full error; smaller refines more (the worst case is far above what the images
    /// show: see docs/benchmarks.md, "Scale").
    #[arg(long, default_value_t = DEFAULT_IMAGE_EPS, value_parser = positive)]
    pub image_eps: f64,
    /// Most leaf tets the client's mesh holds (red leaves; the drawn mesh adds green pieces): a
    /// split beyond is not made, and the frames say the budget binds. Default: a quarter of
    /// this machine's memory at 200 bytes a leaf.
    #[arg(long, value_parser = clap::value_parser!(u64).range(8..))]
    pub max_tets: Option<u64>,
}

impl Default for SelectionArgs {
    fn default() -> Self {
        SelectionArgs {
            criterion: Criterion::Image,
            image_eps: DEFAULT_IMAGE_EPS,
            max_tets: None,
        }
    }
}

fn positive(s: &str) -> Result<f64, crate::options::ArgError> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got {s:?}").into()),
    }
}

impl SelectionArgs {
    /// The leaf budget: `--max-tets`, or [`default_max_tets`].
    pub fn leaf_budget(&self) -> usize {
        self.max_tets
            .map(|m| m.min(usize::MAX as u64) as usize)
            .unwrap_or_else(default_max_tets)
    }

    /// Sets `p`'s criterion and budget for a dataset on `base` drawn with `tf` over
    /// `value_range`.
    pub fn apply(
        &self,
        p: &mut SelectParams,
        tf: &TransferFunction,
        value_range: [f32; 2],
        base: &BaseMesh,
    ) {
        p.max_tets = Some(self.leaf_budget());
        p.image = match self.criterion {
            Criterion::Geometric => None,
            Criterion::Image => Some(tf.image_criterion(value_range, base, self.image_eps)),
        };
    }
}

/// A quarter of this machine's memory at [`BYTES_PER_LEAF`] a leaf (4 GiB assumed where
/// `/proc/meminfo` cannot be read).
pub fn default_max_tets() -> usize {
    (tetwave_store::machine_memory() / 4 / BYTES_PER_LEAF).min(u32::MAX as u64) as usize
}
