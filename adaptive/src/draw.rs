//! The adaptive mesh as the renderers draw it.

use crate::mesh::AdaptiveMesh;
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::BaseMesh;
use tetwave_render::render_mesh::RenderMesh;

/// The drawable leaf mesh of an adaptive mesh (red leaves and green pieces), its scalar range set
/// to `value_range` (the dataset's, so that colours agree from frame to frame), clipped to the
/// domain's level set when `levelset` holds its near band ([`NearLevelSet::value_at`], with the
/// mesh's diameter for `far`), which draws as the exact values do (see
/// [`tetwave_protocol::levelset`]).
pub fn leaf_mesh(
    mesh: &AdaptiveMesh,
    value_range: [f32; 2],
    levelset: Option<&NearLevelSet>,
) -> RenderMesh {
    tets_mesh(
        mesh,
        &mesh.drawable_leaf_tets(),
        value_range,
        levelset,
        false,
    )
}

/// [`leaf_mesh`] of the tets `tets` of `mesh` (its vertex slots), e.g. the coarsened leaf mesh
/// drawn in motion ([`AdaptiveMesh::coarse_leaf_tets`]). With `compact`, the mesh holds only the
/// base vertices and the vertices its tets use (a few tets of a large mesh: the positions to
/// convert and upload are theirs, not every vertex slot's); the base vertices span every vertex's
/// box, so the mesh's diagonal, the transfer function's unit of length, stays the leaf mesh's
/// even where empty tets are left out. Else every vertex slot, by slot.
pub fn tets_mesh(
    mesh: &AdaptiveMesh,
    tets: &[crate::mesh::LeafTet],
    value_range: [f32; 2],
    levelset: Option<&NearLevelSet>,
    compact: bool,
) -> RenderMesh {
    debug_assert!(
        mesh.values_current(),
        "values drawn before AdaptiveMesh::refresh_values (Session::frame does it)"
    );
    // the slots the mesh holds, in its vertex order (`None`: every slot, the mesh's index)
    let (slots, tets): (Option<Vec<u32>>, Vec<[u32; 4]>) = if compact {
        let mut index = vec![u32::MAX; mesh.vertex_slot_len()];
        // base vertices are slots 0..n (AdaptiveMesh::slot_of_key)
        let nbase = mesh.vertex_keys().base_vertex_count() as u32;
        let mut slots: Vec<u32> = (0..nbase).collect();
        index[..nbase as usize].copy_from_slice(&slots);
        let tets = (tets.iter())
            .map(|t| {
                t.v.map(|s| {
                    let i = &mut index[s as usize];
                    if *i == u32::MAX {
                        *i = slots.len() as u32;
                        slots.push(s);
                    }
                    *i
                })
            })
            .collect();
        (Some(slots), tets)
    } else {
        (None, tets.iter().map(|t| t.v).collect())
    };
    let slot = |i: usize| slots.as_ref().map_or(i as u32, |sl| sl[i]);
    let n = slots.as_ref().map_or(mesh.vertex_slot_len(), Vec::len);
    let (all_positions, all_values) = (mesh.positions(), mesh.values());
    let positions = (0..n)
        .map(|i| all_positions[slot(i) as usize].map(|x| x as f64))
        .collect();
    let values = (0..n).map(|i| all_values[slot(i) as usize]).collect();
    let mut m = RenderMesh::new(positions, tets, values);
    m.value_range = (value_range[0], value_range[1]);
    if let Some(near) = levelset {
        let far = m.diagonal() as f32;
        let positions = &m.positions;
        let values = (0..n)
            .map(|i| near.value_at(mesh.vertex_key(slot(i)), positions[i], far))
            .collect();
        m.levelset = Some(values);
    }
    m
}

/// The level set at every vertex of `base`'s hierarchy (by key) as a client draws it from `near`,
/// with the base mesh's diagonal for `far`: what a complete stream's reference image is clipped by.
pub fn every_vertex_levelset(base: &BaseMesh, near: &NearLevelSet) -> Vec<f32> {
    let (lo, hi) = base.bounds();
    let far = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt() as f32;
    let keys = base.vertex_keys();
    let mut out = vec![0f32; keys.vertex_count() as usize];
    for (entity, _) in keys.entities() {
        keys.for_each_in(entity, |key, tet, w| {
            out[key as usize] = near.value_at(key, base.position(tet, &w), far);
        });
    }
    out
}
