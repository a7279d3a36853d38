//! The adaptive mesh as the renderers draw it.

use crate::mesh::AdaptiveMesh;
use tetwave_protocol::levelset::{NearLevelSet, FAR_OUTSIDE};
use tetwave_render::render_mesh::RenderMesh;

/// The drawable leaf mesh of an adaptive mesh (red leaves and green pieces), its scalar range set
/// to `value_range` (the dataset's, so that colours agree from frame to frame), clipped to the
/// domain's level set when `levelset` holds its near band: a far-outside vertex gets minus the
/// mesh's diameter, a vertex not listed (far inside) plus it, which draws as the exact values do
/// (see [`tetwave_protocol::levelset`]).
pub fn leaf_mesh(
    mesh: &AdaptiveMesh,
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
    let tets = mesh.drawable_leaf_tets().iter().map(|t| t.v).collect();
    let mut m = RenderMesh::new(positions, tets, mesh.values().to_vec());
    m.value_range = (value_range[0], value_range[1]);
    if let Some(near) = levelset {
        let far = m.diagonal() as f32;
        m.levelset = Some(
            (0..mesh.vertex_slot_len() as u32)
                .map(|s| levelset_value(near, mesh.vertex_key(s), far))
                .collect(),
        );
    }
    m
}

/// The level set a drawn vertex gets from the band: a listed value as listed, a far-outside one
/// `−far`, an unlisted one (no tet beside the outside has it) `+far`; `far` beyond any tet.
pub fn levelset_value(near: &NearLevelSet, key: u64, far: f32) -> f32 {
    match near.get(key) {
        Some(FAR_OUTSIDE) => -far,
        Some(v) => v,
        None => far,
    }
}
