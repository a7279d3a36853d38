// Visibility order on the GPU (tetwave, gpu/src/sort.rs): a depth key per tet (its centroid's
// squared distance from the eye, as f32 bits, complemented so that ascending keys are back to
// front), then a least-significant-digit radix sort of the (key, tet) pairs, 8 bits a pass, stable.
//
// Each pass is three steps over blocks of `block` consecutive pairs, one invocation per block
// walking its block in order (so the scatter is stable without any ranking inside a block):
// `count` writes the block's digit histogram to `hist[digit * nblocks + block]`; `scan_rows` turns
// each digit's row into exclusive offsets and puts the row's total at `hist[256 * nblocks +
// digit]`; `scan_totals` turns the totals into exclusive digit starts; `scatter` moves each pair to
// its digit's start + its row offset + its rank in the block. The pairs go from `src` to `dst`;
// the host swaps them between passes.

struct Params {
    // x: pairs; y: pairs a block; z: blocks; w: the digit's shift (0, 8, 16, 24)
    counts: vec4<u32>,
    // xyz: the eye, in the centroids' frame
    eye: vec4<f32>,
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> centroids: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> src_keys: array<u32>;
@group(0) @binding(3) var<storage, read_write> src_vals: array<u32>;
@group(0) @binding(4) var<storage, read_write> dst_keys: array<u32>;
@group(0) @binding(5) var<storage, read_write> dst_vals: array<u32>;
@group(0) @binding(6) var<storage, read_write> hist: array<u32>;

// The invocation's index across a 2D dispatch of 64-wide workgroups.
fn flat(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.y * groups.x * 64u + gid.x;
}

@compute @workgroup_size(64)
fn keys(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat(gid, groups);
    if (i >= params.counts.x) {
        return;
    }
    let d = centroids[i].xyz - params.eye.xyz;
    src_keys[i] = ~bitcast<u32>(dot(d, d));
    src_vals[i] = i;
}

@compute @workgroup_size(64)
fn count(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let b = flat(gid, groups);
    let nblocks = params.counts.z;
    if (b >= nblocks) {
        return;
    }
    var c: array<u32, 256>;
    let start = b * params.counts.y;
    let end = min(start + params.counts.y, params.counts.x);
    for (var j = start; j < end; j = j + 1u) {
        let d = (src_keys[j] >> params.counts.w) & 255u;
        c[d] = c[d] + 1u;
    }
    for (var d = 0u; d < 256u; d = d + 1u) {
        hist[d * nblocks + b] = c[d];
    }
}

@compute @workgroup_size(64)
fn scan_rows(@builtin(global_invocation_id) gid: vec3<u32>) {
    let d = gid.x;
    if (d >= 256u) {
        return;
    }
    let nblocks = params.counts.z;
    var sum = 0u;
    for (var b = 0u; b < nblocks; b = b + 1u) {
        let k = d * nblocks + b;
        let x = hist[k];
        hist[k] = sum;
        sum = sum + x;
    }
    hist[256u * nblocks + d] = sum;
}

@compute @workgroup_size(1)
fn scan_totals() {
    let at = 256u * params.counts.z;
    var sum = 0u;
    for (var d = 0u; d < 256u; d = d + 1u) {
        let x = hist[at + d];
        hist[at + d] = sum;
        sum = sum + x;
    }
}

@compute @workgroup_size(64)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let b = flat(gid, groups);
    let nblocks = params.counts.z;
    if (b >= nblocks) {
        return;
    }
    var next: array<u32, 256>;
    for (var d = 0u; d < 256u; d = d + 1u) {
        next[d] = hist[256u * nblocks + d] + hist[d * nblocks + b];
    }
    let start = b * params.counts.y;
    let end = min(start + params.counts.y, params.counts.x);
    for (var j = start; j < end; j = j + 1u) {
        let k = src_keys[j];
        let d = (k >> params.counts.w) & 255u;
        let to = next[d];
        next[d] = to + 1u;
        dst_keys[to] = k;
        dst_vals[to] = src_vals[j];
    }
}
