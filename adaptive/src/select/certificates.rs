//! Motion certificates: how far the camera may move before a slot's criterion could answer
//! otherwise, so that a motion evaluates again only the slots it may change.

use super::cache::PREFETCH;
use super::criteria::{Status, Terms};
use super::{CoarsenRef, FrameCtx, Mode, SegVec, Selector, SCAN_CHUNK};
use crate::mesh::AdaptiveMesh;
use glam::DVec3;
use tetwave_protocol::view::{f32_down, f32_up, View};

/// Motion-bounded re-evaluation (see [`Selector`]): a slot's split criterion, evaluated for one
/// view, keeps its answer while the camera moves less than the slot's *margins*: its distance to
/// the error threshold (the eye moves it at most by the eye's displacement) and, for the frustum,
/// to the planes that decide (a motion moves a plane relative to a scene point at most by the eye's
/// displacement plus the normal's change times the point's distance from the eye). The bounds add
/// up over motions in `we` and `wf`; each slot records the values of those sums at which it must be
/// evaluated again (or sooner, when its node changes).
#[derive(Debug, Clone, Default)]
pub(super) struct Kinetic {
    /// Full epoch whose certificates are held (`None`: not following).
    epoch: Option<u64>,
    /// The view the bounds were last brought to.
    view: Option<View>,
    /// Sums of the motion bounds for the eye distance and for the plane offsets, per unit of a
    /// slot's *reach* `max(|c − o| + r, rho_floor)` (its bounding sphere's farthest distance from
    /// the scene's centre `o`): a rotation by `θ` about `o` moves a point at most `2·sin(θ/2)`
    /// times its distance from `o`, so slots near the centre keep their certificates longer.
    we: f64,
    wf: f64,
    /// Per slot: evaluate again once `we` or `wf` reaches these (rounded down).
    until_e: SegVec<f32>,
    until_f: SegVec<f32>,
    /// Bounding box of the scene (the base vertices), its centre and the least reach counted
    /// (a quarter of its half diagonal: translations and the other bounds divide by it).
    lo: DVec3,
    hi: DVec3,
    centre: DVec3,
    rho_floor: f64,
    scene: bool,
    due: Vec<u32>,
    /// No slot's certificate ends at or below these bounds.
    clean: (f64, f64),
    /// The due pass in progress (the bounds it started from) and its next slot.
    pass: Option<(f64, f64)>,
    cursor: usize,
}

impl Kinetic {
    /// Stops following: the certificates held are no longer trusted.
    pub(super) fn stop(&mut self) {
        self.epoch = None;
    }

    /// Starts a due pass over every slot unless no certificate can have ended since the last one.
    pub(super) fn begin_pass(&mut self) {
        if (self.we, self.wf) != self.clean {
            self.pass = Some((self.we, self.wf));
            self.cursor = 0;
        }
    }

    /// A due pass is in progress.
    pub(super) fn in_pass(&self) -> bool {
        self.pass.is_some()
    }

    /// Bytes held by the per-slot certificates.
    pub(super) fn certificate_bytes(&self) -> usize {
        self.until_e.bytes() + self.until_f.bytes()
    }

    /// The certificate of an evaluation with terms `t` for `view` ([`Selector::eval_cert`]): the
    /// values of `we` and `wf` up to which its answer holds while the node does not change.
    #[inline(always)]
    pub(super) fn certificate(&self, view: &View, frustum: bool, t: &Terms) -> (f32, f32) {
        const INF: f32 = f32::INFINITY;
        let (c, r, d, fac, e) = (t.c, t.r, t.dist, t.weight, t.error);
        let m_e = if fac <= 0.0 || r <= 0.0 || view.tol_px <= 0.0 || !e.is_finite() {
            f64::INFINITY
        } else {
            let big_r = view.pixels_per_unit * 2.0 * r * fac / view.tol_px;
            ((d - big_r).abs() - 1e-9 * (d + big_r) - 1e-12).max(0.0)
        };
        let (we, wf) = (self.we, self.wf);
        // margins in units of the slot's reach (see `Kinetic::we`)
        let reach = ((c - self.centre).length() + r).max(self.rho_floor);
        let m_e = m_e / reach;
        if !frustum {
            return (f32_down(we + m_e), INF);
        }
        let eps = 1e-9 * (c.length() + view.eye.length() + r + 1.0);
        let vals = t.offsets.map(|v| v + r);
        if t.visible {
            if t.over {
                let min = vals.iter().copied().fold(f64::INFINITY, f64::min);
                (
                    f32_down(we + m_e),
                    f32_down(wf + (min - eps).max(0.0) / reach),
                )
            } else {
                (f32_down(we + m_e), INF) // leaving the view keeps it unwanted
            }
        } else {
            let worst = vals.iter().map(|&v| -v).fold(0.0, f64::max);
            let m_f = (worst - eps).max(0.0) / reach;
            // back in view and, unless already, over the threshold: wf bounds both motions
            let m = if t.over { m_f } else { m_f.max(m_e) };
            (INF, f32_down(wf + m))
        }
    }

    /// Bytes held by the due pass's scratch list.
    pub(super) fn scratch_bytes(&self) -> usize {
        self.due.capacity() * 4
    }
}

/// Bit `j` set when slot `j` is due, `ue[j] ≤ we` or `uf[j] ≤ wf`, for up to 64 slots. On x86-64
/// four slots per vector compare (SSE2, always there): a due pass runs it over every slot after a
/// motion, where a compare per slot would be a visible share of the selection's work.
#[inline]
fn due_mask(ue: &[f32], uf: &[f32], we: f32, wf: f32) -> u64 {
    assert!(ue.len() == uf.len() && ue.len() <= 64);
    let mut mask = 0u64;
    let mut j = 0;
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            _mm_cmple_ps, _mm_loadu_ps, _mm_movemask_ps, _mm_or_ps, _mm_set1_ps,
        };
        // SAFETY: SSE2 is part of the x86-64 baseline; every load reads 4 floats at `j < len − 3`.
        unsafe {
            let (vwe, vwf) = (_mm_set1_ps(we), _mm_set1_ps(wf));
            while j + 4 <= ue.len() {
                let e = _mm_cmple_ps(_mm_loadu_ps(ue.as_ptr().add(j)), vwe);
                let f = _mm_cmple_ps(_mm_loadu_ps(uf.as_ptr().add(j)), vwf);
                mask |= (_mm_movemask_ps(_mm_or_ps(e, f)) as u64) << j;
                j += 4;
            }
        }
    }
    for k in j..ue.len() {
        mask |= (((ue[k] <= we) | (uf[k] <= wf)) as u64) << k;
    }
    mask
}

impl Selector {
    /// Whether camera motions are followed by [`Kinetic`] certificates in `mode`.
    pub(super) fn kin_capable(&self, mode: Mode) -> bool {
        !self.reference && mode != Mode::Complete && self.params.coarsen_ref == CoarsenRef::Parent
    }

    pub(super) fn kin_active(&self, mode: Mode) -> bool {
        self.kin.epoch == Some(self.full_epoch) && self.kin_capable(mode)
    }

    /// Starts following camera motions for a full scan with `view`.
    pub(super) fn kin_start(&mut self, mesh: &AdaptiveMesh, view: &View) {
        let k = &mut self.kin;
        if !k.scene {
            let nb = mesh.vertex_keys().base_vertex_count() as u32;
            let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
            for v in 0..nb {
                let p = mesh.vertex_position(v);
                let p = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                lo = lo.min(p);
                hi = hi.max(p);
            }
            k.lo = lo;
            k.hi = hi;
            k.centre = (lo + hi) * 0.5;
            k.rho_floor = ((hi - lo).length() * 0.125).max(1e-9);
            k.scene = true;
        }
        k.epoch = Some(self.full_epoch);
        k.view = Some(*view);
        k.clean = (k.we, k.wf); // once the scan is done
        k.pass = None;
        let len = mesh.node_slot_len();
        k.until_e.clear();
        k.until_f.clear();
        k.until_e.resize(len, f32::NEG_INFINITY);
        k.until_f.resize(len, f32::NEG_INFINITY);
    }

    /// [`Self::eval`], recording the slot's certificate for later motions.
    pub(super) fn eval_kin(&mut self, mesh: &AdaptiveMesh, cx: &FrameCtx, slot: usize) -> Status {
        let (s, ue, uf) = self.eval_cert(mesh, cx, slot, true);
        if slot >= self.kin.until_e.len() {
            let len = mesh.node_slot_len().max(slot + 1);
            self.kin.until_e.resize(len, f32::NEG_INFINITY);
            self.kin.until_f.resize(len, f32::NEG_INFINITY);
        }
        self.kin.until_e[slot] = ue;
        self.kin.until_f[slot] = uf;
        self.remember(slot, s);
        s
    }

    /// The camera moved from `Kinetic::view` to `view`: adds the motion's bounds (the slots whose
    /// certificates they reach are evaluated by the next listed sweep's due pass).
    pub(super) fn kin_advance(&mut self, view: &View) {
        let k = &mut self.kin;
        let old = k.view.expect("following");
        let dm = (view.eye - old.eye).length();
        let dn = (0..5)
            .map(|i| (view.planes[i].0 - old.planes[i].0).length())
            .fold(0.0, f64::max);
        let mut dmax: f64 = 0.0;
        for i in 0..8 {
            let p = DVec3::new(
                if i & 1 == 0 { k.lo.x } else { k.hi.x },
                if i & 2 == 0 { k.lo.y } else { k.hi.y },
                if i & 4 == 0 { k.lo.z } else { k.hi.z },
            );
            dmax = dmax.max((p - view.eye).length());
        }
        // Same lens: the frustum's planes and the eye are fixed in the camera's frame, which moved
        // rigidly. Written as a rotation `R` about the scene's centre `o` and a translation `t`,
        // the motion moves every scene point relative to the camera by at most
        // `|R − I|·ρ + |t| = 2·sin(θ/2)·ρ + |t|` (`ρ`: the scene's radius about `o`), which bounds
        // the change of its distance to the eye and to each plane. An orbit about the scene is
        // a pure rotation: `t = 0`.
        let o = (k.lo + k.hi) * 0.5;
        let rho = (k.hi - k.lo).length() * 0.5;
        let [r0, u0, f0] = old.basis;
        let [r1, u1, f1] = view.basis;
        // |R − I| (operator norm) = 2·sin(θ/2) = |B1 − B0|_F / √2 for orthonormal bases B
        let s2 = (((r1 - r0).length_squared()
            + (u1 - u0).length_squared()
            + (f1 - f0).length_squared())
            * 0.5)
            .sqrt();
        let rot = |v: DVec3| r1 * r0.dot(v) + u1 * u0.dot(v) + f1 * f0.dot(v);
        let t = (view.eye - o - rot(old.eye - o)).length();
        // per unit of reach `ρ' ≥ rho_floor`: a point within `ρ'` of `o` moves at most
        // `s2·ρ' + t ≤ ρ'·(s2 + t/rho_floor)`, and any bound `b` independent of the point is at most
        // `ρ'·b/rho_floor`
        let rf = k.rho_floor;
        let rigid = s2 + t / rf;
        let slack = 1.0 + 1e-6;
        let abs = 1e-9 * (rho + o.length() + view.eye.length() + 1.0) / rf;
        k.we += (dm / rf).min(rigid) * slack + abs;
        k.wf += ((dm + dn * dmax) / rf).min(rigid) * slack + abs;
        k.view = Some(*view);
    }

    /// Evaluates the due slots (certificates used up) among the next `n` slots of the due pass,
    /// listing the candidates; returns the slots looked at. Ends the pass at the last slot.
    pub(super) fn due_pass_step(&mut self, mesh: &AdaptiveMesh, cx: &FrameCtx, n: usize) -> usize {
        let k = &mut self.kin;
        let len = k.until_e.len().min(mesh.node_slot_len());
        let start = k.cursor.min(len);
        let end = (start + n).min(len);
        let mut due = std::mem::take(&mut k.due);
        due.clear();
        // rounded up: a slot in doubt is due
        let (we, wf) = (f32_up(k.we), f32_up(k.wf));
        // stops after a chunk's worth of due slots, so that the caller reads the clock often
        let mut i = start;
        while i < end && due.len() < SCAN_CHUNK {
            let ue = k.until_e.run(i, end);
            let uf = k.until_f.run(i, end);
            let mut off = 0;
            while off < ue.len() && due.len() < SCAN_CHUNK {
                let c = (ue.len() - off).min(64);
                let mut mask = due_mask(&ue[off..off + c], &uf[off..off + c], we, wf);
                while mask != 0 {
                    due.push((i + off) as u32 + mask.trailing_zeros());
                    mask &= mask - 1;
                }
                off += c;
            }
            i += off;
        }
        let end = i;
        k.cursor = end;
        if end == len {
            // every slot is certified beyond the bounds the pass started from
            k.clean = k.pass.take().expect("a pass in progress");
        }
        self.prefetch_slots(mesh, &due, 0, PREFETCH);
        for (j, &slot) in due.iter().enumerate() {
            self.prefetch_slots(mesh, &due, j + PREFETCH, 1);
            if self.eval_kin(mesh, cx, slot as usize) != Status::Keep {
                self.list_add(slot as usize);
            }
        }
        self.kin.due = due;
        end - start
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vector due mask against its definition, on every length up to 64, with values at,
    /// around and beyond the bounds (infinities and NaN included).
    #[test]
    fn due_mask_matches_definition() {
        let vals = [
            f32::NEG_INFINITY,
            -1.0,
            0.5,
            1.0,
            1.0f32.next_up(),
            2.0,
            f32::INFINITY,
            f32::NAN,
        ];
        let mut x = 7u64;
        for len in 0..=64 {
            for _ in 0..50 {
                let mut pick = || {
                    x += 1;
                    vals[(tetwave_protocol::order::splitmix(x) >> 61) as usize]
                };
                let ue: Vec<f32> = (0..len).map(|_| pick()).collect();
                let uf: Vec<f32> = (0..len).map(|_| pick()).collect();
                let (we, wf) = (1.0, 0.5);
                let want = (0..len).fold(0u64, |m, j| {
                    m | (((ue[j] <= we) || (uf[j] <= wf)) as u64) << j
                });
                assert_eq!(due_mask(&ue, &uf, we, wf), want, "{ue:?} {uf:?}");
            }
        }
    }
}
