//! The adaptive mesh as the renderers draw it.

use crate::mesh::AdaptiveMesh;
use tetwave_render::render_mesh::RenderMesh;

/// The drawable leaf mesh of an adaptive mesh (red leaves and green pieces), its scalar range set
/// to `value_range` (the dataset's, so that colours agree from frame to frame).
pub fn leaf_mesh(mesh: &AdaptiveMesh, value_range: [f32; 2]) -> RenderMesh {
    let positions = mesh
        .positions()
        .iter()
        .map(|p| p.map(|x| x as f64))
        .collect();
    let tets = mesh.drawable_leaf_tets().iter().map(|t| t.v).collect();
    let mut m = RenderMesh::new(positions, tets, mesh.values().to_vec());
    m.value_range = (value_range[0], value_range[1]);
    m
}
