// Projected tetrahedra with exit-point integration (tetwave, client/src/render/pt.rs).
//
// Tets are drawn back to front; only each tet's exit faces (outward normal pointing away from the
// eye) are rasterized. The fragment on an exit face knows where the pixel's ray leaves the tet; it finds where the ray
// entered from the tet's face planes (clamped to the near plane, so a camera inside the mesh works),
// evaluates the normalized scalar at both ends from the tet's linear gradient, and integrates
// emission–absorption along the chord with the transfer function (midpoint sub-steps). Output is
// premultiplied; blending is `over` (src ONE, dst ONE_MINUS_SRC_ALPHA).
//
// Spaces: every position is world space relative to `origin` (chosen by the CPU near the mesh's
// centre, so large coordinate offsets do not cost f32 precision).

struct Globals {
    view_proj: mat4x4<f32>,
    // xyz: eye position; w: near-plane distance along the view direction
    eye: vec4<f32>,
    // xyz: unit view direction; w: extinction scale (1 / bounding-box diagonal)
    fwd: vec4<f32>,
    // x: number of transfer-function table intervals; y: scalar resolution for sub-steps (f32 bits);
    // z: max extinction (per diagonal, f32 bits)
    tf_info: vec4<u32>,
};

// Per tet: 4 outward face planes (xyz normal, w offset: n·x = w on the face) and the linear
// normalized scalar s(x) = grad.xyz · x + grad.w.
struct TetGeo {
    planes: array<vec4<f32>, 4>,
    grad: vec4<f32>,
};

// The transfer function tabulated at `tf_info.x + 1` evenly spaced normalized scalars: (r, g, b,
// extinction per diagonal); linear interpolation between entries.
@group(0) @binding(0) var<uniform> globals: Globals;
@group(0) @binding(1) var<storage, read> positions: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> tets: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> geo: array<TetGeo>;
@group(0) @binding(5) var<storage, read> tf: array<vec4<f32>>;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    // ray vector from the eye to this point of the exit face
    @location(0) d: vec3<f32>,
    // per tet, constant over it (no buffer reads in the fragment stage but the transfer function):
    // the x, y and z components of the 4 outward face normals, the 4 offsets `w_i - n_i·eye` (the
    // ray `eye + t·dir` meets plane `i` at `t = c_i / (n_i·dir)`), and the scalar gradient with the
    // scalar extended to the eye in `w`
    @location(1) @interpolate(flat) nx: vec4<f32>,
    @location(2) @interpolate(flat) ny: vec4<f32>,
    @location(3) @interpolate(flat) nz: vec4<f32>,
    @location(4) @interpolate(flat) c: vec4<f32>,
    @location(5) @interpolate(flat) grad: vec4<f32>,
};

// Indexed draw: vertex `v` is corner `v % 4` of tet `v / 4`; the CPU's index buffer lists, in
// back-to-front tet order, only each tet's exit faces (outward winding counter-clockwise), and the
// rasterizer also culls front faces, so only exit faces reach the fragment stage.
@vertex
fn vs_main(@builtin(vertex_index) vi: u32) -> VsOut {
    let t = vi / 4u;
    let p = positions[tets[t][vi % 4u]].xyz;
    let eye = globals.eye.xyz;
    let g = geo[t];
    let pl = g.planes;
    var out: VsOut;
    out.d = p - eye;
    out.nx = vec4<f32>(pl[0].x, pl[1].x, pl[2].x, pl[3].x);
    out.ny = vec4<f32>(pl[0].y, pl[1].y, pl[2].y, pl[3].y);
    out.nz = vec4<f32>(pl[0].z, pl[1].z, pl[2].z, pl[3].z);
    out.c = vec4<f32>(pl[0].w, pl[1].w, pl[2].w, pl[3].w)
        - (out.nx * eye.x + out.ny * eye.y + out.nz * eye.z);
    out.grad = vec4<f32>(g.grad.xyz, dot(g.grad.xyz, eye) + g.grad.w);
    out.clip = globals.view_proj * vec4<f32>(p, 1.0);
    return out;
}

fn tf_eval(s: f32) -> vec4<f32> {
    // returns (r, g, b, extinction per diagonal), clamped at the ends
    let n = globals.tf_info.x;
    let x = clamp(s, 0.0, 1.0) * f32(n);
    let k = min(u32(x), n - 1u);
    return mix(tf[k], tf[k + 1u], x - f32(k));
}

@fragment
fn fs_main(in: VsOut) -> @location(0) vec4<f32> {
    let t_exit = length(in.d);
    if (!(t_exit > 0.0)) {
        discard;
    }
    let dir = in.d / t_exit;
    // rays start at the near plane; the entry is the farthest crossing of a plane the ray enters by
    let den = in.nx * dir.x + in.ny * dir.y + in.nz * dir.z;
    let hits = select(vec4<f32>(-1e30), in.c / den, den < vec4<f32>(0.0));
    let t_near = globals.eye.w / max(dot(dir, globals.fwd.xyz), 1e-6);
    let t_in = max(t_near, max(max(hits.x, hits.y), max(hits.z, hits.w)));
    let len = t_exit - t_in;
    if (!(len > 0.0) || len > 1e30) {
        discard;
    }
    let gd = dot(in.grad.xyz, dir);
    let s0 = in.grad.w + t_in * gd;
    let s1 = in.grad.w + t_exit * gd;
    let ext_scale = globals.fwd.w;
    let s_res = bitcast<f32>(globals.tf_info.y);
    // sub-steps: each step uses the exact absorption of its own constant extinction, so the error
    // comes only from the transfer function varying within a step: bound the scalar change per step
    let steps = u32(clamp(ceil(abs(s1 - s0) / s_res), 1.0, 64.0));
    if (steps == 1u) {
        let e = tf_eval(0.5 * (s0 + s1));
        let a = 1.0 - exp(-e.w * ext_scale * len);
        return vec4<f32>(e.xyz * a, a);
    }
    let h = len / f32(steps);
    var col = vec3<f32>(0.0);
    var tr = 1.0;
    for (var i = 0u; i < steps; i = i + 1u) {
        let u = (f32(i) + 0.5) / f32(steps);
        let e = tf_eval(mix(s0, s1, u));
        let a = 1.0 - exp(-e.w * ext_scale * h);
        col = col + tr * e.xyz * a;
        tr = tr * (1.0 - a);
    }
    return vec4<f32>(col, 1.0 - tr);
}
