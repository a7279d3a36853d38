//! The criteria: what a node's bounding sphere, subtree max and the view say of it, uncached
//! ([`Selector::want_split`], [`Selector::want_merge`]) and through the per-slot caches.

use super::{CoarsenRef, FrameCtx, Mode, Selector};
use crate::detail_buffer::DetailBuffer;
use crate::mesh::{AdaptiveMesh, RedNode};
use glam::{DVec3, Vec3};
use tetwave_protocol::view::{data_weight, tet_sphere, ImageCriterion, View};
use tetwave_protocol::TetId;

/// The facts of one node the criteria read ([`Selector::info_of`] gives them from its cache entry).
#[derive(Debug, Clone, Copy)]
pub(super) struct SlotInfo {
    pub(super) smax: f32,
    pub(super) level: u8,
    pub(super) present: bool,
    pub(super) usable: bool,
}

/// Bounding sphere of mesh vertices `v`: the centroid rounded to `f32`, and the distance from it to
/// the farthest vertex rounded up to `f32` (so that selection caches it in 16 bytes, exactly).
#[inline]
pub fn bounding_sphere(mesh: &AdaptiveMesh, v: &[u32; 4]) -> (DVec3, f64) {
    let (c, r) = sphere32(mesh, v);
    (c.as_dvec3(), r as f64)
}

/// [`bounding_sphere`] as selection caches it, in `f32`.
#[inline]
pub(super) fn sphere32(mesh: &AdaptiveMesh, v: &[u32; 4]) -> (Vec3, f32) {
    let pos = mesh.positions();
    tet_sphere(v.map(|s| {
        let q = pos[s as usize];
        DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64)
    }))
}

/// The merge priority of a node outside the frustum (below every in-view error, so merged first).
pub(super) const OUTSIDE: f64 = -1.0;

/// What the criteria want of one node of the red tree.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Status {
    Keep,
    /// A leaf wanted split, with its priority.
    Split(f64),
    /// A refined node with 8 leaf children whose split should be undone, with its priority.
    Merge(f64),
}

/// The terms of one evaluation of the split criterion that its certificate uses again
/// ([`super::certificates::Kinetic::certificate`]).
pub(super) struct Terms {
    /// The bounding sphere.
    pub(super) c: DVec3,
    pub(super) r: f64,
    /// [`View::plane_offsets`] of the centre.
    pub(super) offsets: [f64; 5],
    /// Distance from the eye to the centre.
    pub(super) dist: f64,
    /// The data weight.
    pub(super) weight: f64,
    /// The weighted screen-space error.
    pub(super) error: f64,
    /// Inside the frustum (or not culling).
    pub(super) visible: bool,
    /// The error is over the tolerance.
    pub(super) over: bool,
}

impl Selector {
    /// Split priority of leaf `n`: `Some(error)` when it is wanted split.
    pub fn want_split(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: &RedNode,
    ) -> Option<f64> {
        let forest = mesh.forest();
        if n.empty || !buf.is_present(n.id) {
            return None;
        }
        let level = forest.level(n.id);
        if level >= forest.levels || !buf.is_usable(n.id) {
            return None;
        }
        if mode == Mode::Complete {
            return Some((forest.levels - level) as f64);
        }
        let e = self.error(mesh, buf, view, n)?;
        (e > view.tol_px).then_some(e)
    }

    /// Whether leaf `n`, whose own store node has not arrived (or is still a preview), stays
    /// unsplit under the last frame's camera whatever that node brings: the subtree bound of its
    /// nearest held ancestor covers its subtree, and with that bound in its place the criterion
    /// does not split it (or culls it). Every weight grows with the bound, so the node's own,
    /// smaller bound cannot split it either. Complete mode splits whatever arrives: never.
    pub fn stays_unsplit_without_node(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        n: &RedNode,
    ) -> bool {
        let (Some(cam), Some(mode)) = (self.last_cam.as_ref(), self.last_mode) else {
            return false;
        };
        if mode == Mode::Complete {
            return false;
        }
        let forest = mesh.forest();
        let mut up = forest.parent(n.id);
        let smax = loop {
            let Some(a) = up else { return false };
            if let Some(m) = buf.subtree_max(a).filter(|_| !buf.is_preview(a)) {
                break m;
            }
            up = forest.parent(a);
        };
        let view = View::new(cam, self.params.tol);
        let slot = n.slot as usize;
        let (c, r) = bounding_sphere(mesh, &mesh.node_verts(slot));
        let fac = self.node_weight(mesh, slot, forest.level(n.id), Some(smax), r);
        self.sphere_error(&view, c, r, fac)
            .is_none_or(|e| e <= view.tol_px)
    }

    /// Data-aware screen-space error of `n`; `None` outside the frustum (when culling).
    fn error(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        n: &RedNode,
    ) -> Option<f64> {
        let slot = n.slot as usize;
        let (c, r) = bounding_sphere(mesh, &mesh.node_verts(slot));
        let level = mesh.forest().level(n.id);
        let fac = self.node_weight(mesh, slot, level, buf.subtree_max(n.id), r);
        self.sphere_error(view, c, r, fac)
    }

    /// [`Self::error`] of a node with bounding sphere `(c, r)` and weight `fac`.
    #[inline]
    fn sphere_error(&self, view: &View, c: DVec3, r: f64, fac: f64) -> Option<f64> {
        if self.params.frustum && !view.sphere_visible(c, r) {
            return None;
        }
        Some(view.error_px(c, 2.0 * r) * fac)
    }

    /// The data weight of a node with subtree max `smax` (1 unless data-aware with one).
    #[inline]
    pub(super) fn weight(&self, smax: Option<f32>) -> f64 {
        match (self.params.data_aware, smax) {
            (Some(delta), Some(m)) => data_weight(m, self.params.value_range, delta),
            _ => 1.0,
        }
    }

    /// The weight of the node in `slot` (at `level`, subtree max `smax`, bounding radius `r`):
    /// with the image criterion ([`SelectParams::image`]) its [`image_weight`], otherwise
    /// [`Self::weight`]. A node whose subtree max is unknown (not held) weighs 1.
    #[inline]
    pub(super) fn node_weight(
        &self,
        mesh: &AdaptiveMesh,
        slot: usize,
        level: u8,
        smax: Option<f32>,
        r: f64,
    ) -> f64 {
        match (&self.params.image, smax) {
            (Some(img), Some(m)) => image_weight(img, mesh, slot, level, m, r),
            (Some(_), None) => 1.0,
            (None, _) => self.weight(smax),
        }
    }

    /// Merge priority of refined node `n` (children all leaves): `Some(error)` when its split
    /// should be undone.
    pub fn want_merge(
        &self,
        mesh: &AdaptiveMesh,
        buf: &DetailBuffer,
        view: &View,
        mode: Mode,
        n: &RedNode,
    ) -> Option<f64> {
        if self.want_split(mesh, buf, view, mode, n).is_some() {
            return None;
        }
        if self.params.coarsen_ref == CoarsenRef::Grandparent && mode != Mode::Complete {
            if let Some(p) = mesh.forest().parent(n.id) {
                if let Some(pn) = mesh.red_node_of(p) {
                    if self.want_split(mesh, buf, view, mode, &pn).is_some() {
                        return None;
                    }
                }
            }
        }
        Some(if mode == Mode::Complete {
            0.0
        } else {
            self.error(mesh, buf, view, n).unwrap_or(OUTSIDE)
        })
    }

    /// The status of node `n` by [`Self::want_split`] / [`Self::want_merge`] (the reference
    /// selector's, no cache).
    pub(super) fn status_uncached(
        &self,
        mesh: &AdaptiveMesh,
        cx: &FrameCtx,
        n: &RedNode,
    ) -> Status {
        if n.leaf {
            if let Some(e) = self.want_split(mesh, cx.buf, cx.view, cx.mode, n) {
                return Status::Split(e);
            }
        } else if n.children_leaves {
            if let Some(e) = self.want_merge(mesh, cx.buf, cx.view, cx.mode, n) {
                return Status::Merge(e);
            }
        }
        Status::Keep
    }

    // ------------------------------------------------------------ cached criteria

    /// [`Self::want_split`] from the cache.
    #[inline]
    fn split_cached(
        &mut self,
        mesh: &AdaptiveMesh,
        cx: &FrameCtx,
        slot: usize,
        n: &RedNode,
    ) -> (Option<f64>, SlotInfo) {
        let levels = mesh.forest().levels;
        let i = self.info_of(mesh, cx.buf, slot, n);
        if n.empty || !i.usable || i.level >= levels {
            return (None, i);
        }
        if cx.mode == Mode::Complete {
            return (Some((levels - i.level) as f64), i);
        }
        let (c, r) = self.sphere_of(mesh, slot);
        let fac = self.node_weight(mesh, slot, i.level, Some(i.smax), r);
        let e = self
            .sphere_error(cx.view, c, r, fac)
            .filter(|&e| e > cx.view.tol_px);
        (e, i)
    }

    /// The status of the live node in `slot` (the cached [`Self::want_split`] /
    /// [`Self::want_merge`]).
    #[inline]
    pub(super) fn eval(&mut self, mesh: &AdaptiveMesh, cx: &FrameCtx, slot: usize) -> Status {
        // the status is a function of the node for one epoch: reused unless the slot changed
        // since (changes not yet read from the mesh could concern it)
        if self.seen == mesh.change_seq() && !self.reference {
            if let Some(&e) = self.info.get(slot) {
                if e.epoch() == self.stat_epoch() {
                    return self.cached_status(cx, mesh.forest().levels, slot, &e);
                }
            }
        }
        let st = self.eval_cert(mesh, cx, slot, false).0;
        self.remember(slot, st);
        st
    }

    /// [`Self::eval`], and with `cert` the slot's certificate (see
    /// [`super::certificates::Kinetic`]): the values of `we` and `wf` up to which its status cannot
    /// change without a change of its node.
    #[inline(always)]
    pub(super) fn eval_cert(
        &mut self,
        mesh: &AdaptiveMesh,
        cx: &FrameCtx,
        slot: usize,
        cert: bool,
    ) -> (Status, f32, f32) {
        const INF: f32 = f32::INFINITY;
        self.evals += 1;
        let Some(n) = mesh.red_node(slot) else {
            return (Status::Keep, INF, INF);
        };
        if !n.leaf && !n.children_leaves {
            return (Status::Keep, INF, INF);
        }
        let levels = mesh.forest().levels;
        let i = self.info_of(mesh, cx.buf, slot, &n);
        if n.empty || !i.usable || i.level >= levels {
            // not wanted split, whatever the view
            if n.leaf {
                return (Status::Keep, INF, INF);
            }
            return (self.merge_status(mesh, cx, slot, &n, i), INF, INF);
        }
        if cx.mode == Mode::Complete {
            let s = if n.leaf {
                Status::Split((levels - i.level) as f64)
            } else {
                Status::Keep
            };
            return (s, INF, INF);
        }
        // the criterion, as `want_split` computes it
        let (c, r) = self.sphere_of(mesh, slot);
        // `View::sphere_visible` and `Self::weighted_error` in steps whose terms the certificate
        // uses again
        let x = cx.view.plane_offsets(c);
        let visible = !self.params.frustum || View::offsets_visible(&x, r);
        let d = (c - cx.view.eye).length();
        let fac = self.node_weight(mesh, slot, i.level, Some(i.smax), r);
        self.keep_weight(slot, fac);
        let e = cx.view.error_px_at(d, 2.0 * r) * fac;
        let err = e > cx.view.tol_px;
        let status = if n.leaf {
            if visible && err {
                Status::Split(e)
            } else {
                Status::Keep
            }
        } else if (visible && err)
            || (self.params.coarsen_ref == CoarsenRef::Grandparent
                && self.parent_wants_split(mesh, cx, &n))
        {
            Status::Keep
        } else {
            Status::Merge(if visible { e } else { OUTSIDE })
        };
        if !cert {
            return (status, INF, INF);
        }
        let terms = Terms {
            c,
            r,
            offsets: x,
            dist: d,
            weight: fac,
            error: e,
            visible,
            over: err,
        };
        let (ue, uf) = self.kin.certificate(cx.view, self.params.frustum, &terms);
        (status, ue, uf)
    }

    /// Grandparent rule: whether the parent of refined node `n` is wanted split.
    fn parent_wants_split(&mut self, mesh: &AdaptiveMesh, cx: &FrameCtx, n: &RedNode) -> bool {
        if let Some(p) = mesh.forest().parent(n.id) {
            if let Some(ps) = mesh.slot_of(p) {
                let pn = mesh.red_node(ps).expect("slot_of gives live slots");
                return self.split_cached(mesh, cx, ps, &pn).0.is_some();
            }
        }
        false
    }

    /// Merge status of refined node `n` (8 leaf children) that is not wanted split.
    fn merge_status(
        &mut self,
        mesh: &AdaptiveMesh,
        cx: &FrameCtx,
        slot: usize,
        n: &RedNode,
        i: SlotInfo,
    ) -> Status {
        if cx.mode == Mode::Complete {
            return Status::Merge(0.0);
        }
        if self.params.coarsen_ref == CoarsenRef::Grandparent
            && self.parent_wants_split(mesh, cx, n)
        {
            return Status::Keep;
        }
        let smax = i.present.then_some(i.smax);
        let (c, r) = self.sphere_of(mesh, slot);
        let fac = self.node_weight(mesh, slot, i.level, smax, r);
        self.keep_weight(slot, fac);
        Status::Merge(self.sphere_error(cx.view, c, r, fac).unwrap_or(OUTSIDE))
    }

    /// The status of hierarchy tet `id` (not in the red tree: [`Status::Keep`]) and its slot;
    /// `hint`: the slot it probably is in.
    pub(super) fn status_of(
        &mut self,
        mesh: &AdaptiveMesh,
        cx: &FrameCtx,
        id: TetId,
        hint: u32,
    ) -> (Status, u32) {
        if self.reference {
            let Some(n) = mesh.red_node_of(id) else {
                return (Status::Keep, u32::MAX);
            };
            return (self.status_uncached(mesh, cx, &n), u32::MAX);
        }
        let slot = if mesh.slot_holds(hint as usize, id) {
            Some(hint as usize)
        } else {
            mesh.slot_of(id)
        };
        match slot {
            Some(s) => (self.eval(mesh, cx, s), s as u32),
            None => (Status::Keep, u32::MAX),
        }
    }
}

/// The image criterion's weight of the node in `slot` ([`ImageCriterion::node_weight`] over the
/// values the mesh holds, rounded to `f32` so that a weight kept in the cache is the weight
/// computed again). The curvature term reads the node's level-`l` corners and the ends of the
/// parent edges they halve.
pub(super) fn image_weight(
    img: &ImageCriterion,
    mesh: &AdaptiveMesh,
    slot: usize,
    level: u8,
    smax: f32,
    r: f64,
) -> f64 {
    let verts = mesh.node_verts(slot);
    let vals = mesh.values();
    let v = verts.map(|s| vals[s as usize]);
    let mut curvature = 0.0f64;
    for (k, &s) in verts.iter().enumerate() {
        if level > 0 && mesh.vertex_level(s) == level {
            if let Some([a, b]) = mesh.vertex_ends(s) {
                let mid = 0.5 * (vals[a as usize] as f64 + vals[b as usize] as f64);
                curvature = curvature.max((v[k] as f64 - mid).abs());
            }
        }
    }
    img.node_weight(v, curvature, level, mesh.forest().levels, smax, 2.0 * r)
}
