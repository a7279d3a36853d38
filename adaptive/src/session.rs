//! A client session: the detail buffer, the adaptive mesh and the selector, wired once.
//!
//! Everything that consumes a stream (the network client, the progressive benchmark, a viewer) goes
//! through a [`Session`]: arrived nodes go into the buffer, their vertices and metadata into the
//! mesh, their ids to the selector; a frame refines the mesh for a camera under the selector's
//! budget. The mesh always reflects exactly the nodes the buffer holds, so every frame draws a
//! conforming mesh of what has arrived.

use crate::detail_buffer::{Arrivals, BufferError, DetailBuffer, Inserted};
use crate::mesh::{AdaptiveMesh, MeshError};
use crate::select::{FrameStats, Mode, SelectParams, Selector};
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::view::Camera;
use tetwave_protocol::{BaseMesh, DetailNode, TetId};
use tetwave_render::render_mesh::RenderMesh;

/// A node the buffer refused (out of range, malformed, or claiming another node's vertex).
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("detail node {id} is invalid: {source}")]
pub struct NodeRejected {
    pub id: TetId,
    #[source]
    pub source: BufferError,
}

/// What one [`Session::insert`] (or [`Session::insert_preview`]) did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Inserts {
    /// Nodes not held before (a store's node that replaced its preview included).
    pub new: usize,
    /// Nodes already held (ignored).
    pub duplicates: usize,
}

/// The buffer, mesh and selector of one dataset.
pub struct Session {
    base: BaseMesh,
    buf: DetailBuffer,
    mesh: AdaptiveMesh,
    sel: Selector,
    arrivals: Arrivals,
    /// The near band of the domain's level set, once fetched: drawn meshes are clipped to it.
    levelset: Option<NearLevelSet>,
}

impl Session {
    /// A session on `base` with a selector of `params`.
    pub fn new(base: BaseMesh, params: SelectParams) -> Result<Self, MeshError> {
        Self::with_selector(base, Selector::new(params))
    }

    /// A session with a given selector (e.g. [`Selector::full_scan`]).
    pub fn with_selector(base: BaseMesh, sel: Selector) -> Result<Self, MeshError> {
        let mesh = AdaptiveMesh::new(&base)?;
        let buf = DetailBuffer::new(base.forest(), base.vertex_keys());
        Ok(Session {
            base,
            buf,
            mesh,
            sel,
            arrivals: Arrivals::default(),
            levelset: None,
        })
    }

    /// Takes arrived nodes, in any order and with duplicates. Stops at the first invalid node: the
    /// nodes before it are held and applied, it and the ones after it are not. With the axes
    /// predictor the mesh's values catch up at the next [`Self::frame`] or [`Self::converge`].
    pub fn insert<'a>(
        &mut self,
        nodes: impl IntoIterator<Item = &'a DetailNode>,
    ) -> Result<Inserts, NodeRejected> {
        self.take(nodes, DetailBuffer::insert)
    }

    /// Takes preview nodes ([`DetailBuffer::insert_preview`]) as [`Self::insert`] takes the
    /// store's.
    pub fn insert_preview<'a>(
        &mut self,
        nodes: impl IntoIterator<Item = &'a DetailNode>,
    ) -> Result<Inserts, NodeRejected> {
        self.take(nodes, DetailBuffer::insert_preview)
    }

    fn take<'a>(
        &mut self,
        nodes: impl IntoIterator<Item = &'a DetailNode>,
        insert: fn(&mut DetailBuffer, &DetailNode, &mut Arrivals) -> Result<Inserted, BufferError>,
    ) -> Result<Inserts, NodeRejected> {
        self.arrivals.clear();
        let mut done = Inserts::default();
        let mut rejected = None;
        for n in nodes {
            match insert(&mut self.buf, n, &mut self.arrivals) {
                Ok(Inserted::New | Inserted::Replaced) => done.new += 1,
                Ok(Inserted::Duplicate) => done.duplicates += 1,
                Err(source) => {
                    rejected = Some(NodeRejected { id: n.id, source });
                    break;
                }
            }
        }
        if !self.arrivals.is_empty() {
            let changed = self.mesh.apply_arrivals(&self.buf, &self.arrivals);
            self.values_changed(changed);
            if self.arrivals.replaced.is_empty() {
                self.sel.notify_arrived(&self.mesh, &self.arrivals.nodes);
            } else {
                // a replaced node was usable already, its subtree too: only its metadata changed
                // (notify_replaced), so only the others' subtrees are walked
                let replaced: rustc_hash::FxHashSet<TetId> =
                    self.arrivals.replaced.iter().copied().collect();
                let fresh: Vec<TetId> = (self.arrivals.nodes.iter())
                    .filter(|id| !replaced.contains(id))
                    .copied()
                    .collect();
                self.sel
                    .notify_replaced(&self.mesh, &self.arrivals.replaced);
                self.sel.notify_arrived(&self.mesh, &fresh);
            }
        }
        match rejected {
            Some(r) => Err(r),
            None => Ok(done),
        }
    }

    /// One frame of selective refinement for `cam`, within the selector's budget for `mode`
    /// (first bringing vertex values up to the nodes held, where arrivals defer that).
    pub fn frame(&mut self, cam: &Camera, mode: Mode) -> Result<FrameStats, MeshError> {
        let changed = self.mesh.refresh_values(&self.buf);
        self.values_changed(changed);
        self.sel.frame(&mut self.mesh, &self.buf, cam, mode)
    }

    /// Refines until the selector is satisfied for `cam`, whatever the budget.
    pub fn converge(&mut self, cam: &Camera, mode: Mode) -> Result<FrameStats, MeshError> {
        let changed = self.mesh.refresh_values(&self.buf);
        self.values_changed(changed);
        self.sel.converge(&mut self.mesh, &self.buf, cam, mode)
    }

    /// `changed` present vertex values moved when they were brought up to the coefficients held:
    /// the image criterion reads vertex values, so its statuses are looked at again (the other
    /// criteria read none).
    fn values_changed(&mut self, changed: usize) {
        if changed > 0 && self.sel.params.image.is_some() {
            self.sel.notify_arrivals();
        }
    }

    /// Replaces the selector's parameters (criterion, budget, transfer function's sensitivity);
    /// the next frame looks at the whole mesh again when they changed.
    pub fn set_params(&mut self, params: SelectParams) {
        if self.sel.params != params {
            self.sel.params = params;
            self.sel.notify_arrivals();
        }
    }

    /// Changes the selector's tolerance; the next frame looks at the whole mesh again.
    pub fn set_tolerance(&mut self, tol: crate::select::Tolerance) {
        if self.sel.params.tol != tol {
            self.sel.params.tol = tol;
            self.sel.notify_arrivals();
        }
    }

    /// Whether the last frame left nothing to do for its camera and the nodes held.
    pub fn is_converged(&self) -> bool {
        self.sel.is_converged()
    }

    /// Whether the mesh is final for the last frame's camera whatever arrives next: the selector
    /// converged, and every leaf it could still split either holds its store node (not a
    /// preview), whose subtree bound told the criterion that the image needs nothing below it,
    /// or stays unsplit under its nearest held ancestor's bound, which covers its subtree
    /// ([`Selector::stays_unsplit_without_node`]): so a client needs the nodes of its leaves only
    /// where their parent's bound cannot settle them. Later arrivals may still correct vertex
    /// values in place (by at most the missing details). One pass over the mesh's nodes.
    pub fn view_complete(&self) -> bool {
        self.sel.is_converged() && !self.unsettled(|_| false)
    }

    /// The nodes the last frame's camera needs and the session does not hold: the leaves
    /// [`Self::view_complete`] waits for (a splittable leaf without its store node that its
    /// nearest held ancestor's bound cannot settle). What a reader that fetches nodes itself (a
    /// store in a bucket, with no server choosing) asks for next. One pass over the mesh's nodes.
    pub fn wanted(&self) -> Vec<TetId> {
        let mut out = Vec::new();
        self.unsettled(|id| {
            out.push(id);
            true
        });
        out
    }

    /// Hands each unsettled leaf to `f` while it returns true; whether there was one.
    fn unsettled(&self, mut f: impl FnMut(TetId) -> bool) -> bool {
        let (mut any, mut go) = (false, true);
        self.mesh.for_each_splittable_leaf(|id| {
            if !go || (self.buf.is_present(id) && !self.buf.is_preview(id)) {
                return;
            }
            let settled = self.mesh.red_node_of(id).is_some_and(|n| {
                self.sel
                    .stays_unsplit_without_node(&self.mesh, &self.buf, &n)
            });
            if !settled {
                any = true;
                go = f(id);
            }
        });
        any
    }

    /// The selector's parameters (tolerance, budgets).
    pub fn params(&self) -> &SelectParams {
        &self.sel.params
    }

    /// Sets the budget of [`Mode::Interactive`] frames (it changes no criterion: the mesh wanted
    /// stays the same, only how much of the way there a frame goes).
    pub fn set_interactive_budget(&mut self, budget: crate::select::Budget) {
        self.sel.params.interactive = budget;
    }

    pub fn base(&self) -> &BaseMesh {
        &self.base
    }

    pub fn mesh(&self) -> &AdaptiveMesh {
        &self.mesh
    }

    pub fn buffer(&self) -> &DetailBuffer {
        &self.buf
    }

    pub fn selector(&self) -> &Selector {
        &self.sel
    }

    /// Nodes held, of the hierarchy's total.
    pub fn progress(&self) -> (u64, u64) {
        (self.buf.nodes_held(), self.base.forest().nodes())
    }

    /// Whether every node of the hierarchy is held.
    pub fn is_complete(&self) -> bool {
        let (held, total) = self.progress();
        held == total
    }

    /// The drawable leaf mesh, its colours mapped over `value_range`, clipped to the level set
    /// when the session has one.
    pub fn leaf_mesh(&self, value_range: [f32; 2]) -> RenderMesh {
        crate::draw::leaf_mesh(&self.mesh, value_range, self.levelset.as_ref())
    }

    /// [`Self::leaf_mesh`], and with `most > 0` that mesh coarsened to at most `most` tets to
    /// draw while the camera moves ([`AdaptiveMesh::coarse_leaf_tets`], holding only its own
    /// vertices; `None` when the leaf mesh has no more than `most` tets). The leaves are listed
    /// once for both.
    pub fn leaf_meshes(
        &self,
        value_range: [f32; 2],
        most: usize,
    ) -> (RenderMesh, Option<RenderMesh>) {
        let tets = self.mesh.drawable_leaf_tets();
        let levelset = self.levelset.as_ref();
        let motion = (most > 0 && tets.len() > most).then(|| {
            let coarse = self.mesh.coarsened(tets.clone(), most);
            crate::draw::tets_mesh(&self.mesh, &coarse, value_range, levelset, true)
        });
        let leaf = crate::draw::tets_mesh(&self.mesh, &tets, value_range, levelset, false);
        (leaf, motion)
    }

    /// Clips every mesh drawn from now on to the domain's level set (its near band, as
    /// `/v1/levelset` serves it).
    pub fn set_levelset(&mut self, near: NearLevelSet) {
        self.levelset = Some(near);
    }

    /// Whether drawn meshes are clipped to a level set.
    pub fn has_levelset(&self) -> bool {
        self.levelset.is_some()
    }

    /// The level set's near band drawn meshes are clipped to.
    pub fn levelset(&self) -> Option<&NearLevelSet> {
        self.levelset.as_ref()
    }

    /// The session's parts, for a caller that ends it (e.g. to check the final mesh).
    pub fn into_parts(self) -> (BaseMesh, DetailBuffer, AdaptiveMesh, Selector) {
        (self.base, self.buf, self.mesh, self.sel)
    }
}
