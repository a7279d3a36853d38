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
    tets_mesh(mesh, &mesh.drawable_leaf_tets(), value_range, levelset)
}

/// [`leaf_mesh`] of the tets `tets` of `mesh` (its vertex slots), e.g. the coarsened leaf mesh
/// drawn in motion ([`AdaptiveMesh::coarse_leaf_tets`]).
pub fn tets_mesh(
    mesh: &AdaptiveMesh,
    tets: &[crate::mesh::LeafTet],
    value_range: [f32; 2],
    levelset: Option<&NearLevelSet>,
) -> RenderMesh {
    debug_assert!(
        mesh.values_current(),
        "values drawn before AdaptiveMesh::refresh_values (Session::frame does it)"
    );
    let positions: Vec<[f64; 3]> = mesh
        .positions()
        .iter()
        .map(|p| p.map(|x| x as f64))
        .collect();
    let tets = tets.iter().map(|t| t.v).collect();
    let mut m = RenderMesh::new(positions, tets, mesh.values().to_vec());
    m.value_range = (value_range[0], value_range[1]);
    if let Some(near) = levelset {
        let far = m.diagonal() as f32;
        let positions = &m.positions;
        let values = (0..mesh.vertex_slot_len() as u32)
            .map(|s| near.value_at(mesh.vertex_key(s), positions[s as usize], far))
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
