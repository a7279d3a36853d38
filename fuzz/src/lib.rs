//! What the fuzz targets check, shared by the libFuzzer target and the stable "smoke" runner:
//! the wire decoders are total (an error value, never a panic, for any bytes), and a frame that
//! decodes re-encodes to a frame that decodes to the same bytes again (idempotent round trip); a
//! `Nodes` or `Preview` frame's block decodes (with the coders of a small hierarchy, lossless and
//! quantized) to valid nodes or to an error, never a panic, and what decodes re-codes to the same nodes; every
//! input is also fed to the block decoder directly as a block's coded bytes, and to the level-set
//! band decoder (`/v1/levelset`), whose results re-code to themselves.

pub mod volume;

use std::sync::OnceLock;
use tetwave_protocol::block::{BlockCoder, NodeBlock};
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::shapes::box5;
use tetwave_protocol::store_format::Encoding;
use tetwave_protocol::wire::{
    decode_client, decode_server, encode, frame_len, ClientMsg, IdRange, ServerMsg, SessionStart,
    ViewParams, PROTOCOL_VERSION,
};
use tetwave_protocol::{BaseMesh, DetailNode};

/// A level-3 box5 hierarchy: 365 nodes.
fn base() -> BaseMesh {
    let (positions, tets) = box5([0.0; 3], [1.0; 3]);
    BaseMesh {
        levels: 3,
        values: vec![0.0; positions.len()],
        empty: vec![false; tets.len()],
        predictor: Default::default(),
        positions,
        tets,
    }
}

/// The block coders the checks decode with: lossless, 12-bit quantized, and 12-bit with the
/// steepest level steps a manifest may name.
fn coders() -> &'static [BlockCoder; 4] {
    static C: OnceLock<[BlockCoder; 4]> = OnceLock::new();
    C.get_or_init(|| {
        let b = base();
        let steep = tetwave_protocol::wavelet::LevelSteps {
            ratio: 16.0,
            cap: 16.0,
        };
        [
            BlockCoder::new(&b, &Encoding::F32),
            BlockCoder::new(&b, &Encoding::uniform(12, 0.01)),
            BlockCoder::new(
                &b,
                &Encoding::Quantized {
                    bits: 12,
                    step: 0.01,
                    levels: steep,
                },
            ),
            // a preview's: no subtree bound on any node
            BlockCoder::for_preview(&b, &Encoding::uniform(8, 0.5)),
        ]
    })
}

/// Runs every check on one input; panics (a finding) only if a property fails.
pub fn check(data: &[u8]) {
    let _ = frame_len(data);
    if let Ok(m) = decode_client(data) {
        let once = encode(&m).expect("a decoded client message re-encodes");
        let back = decode_client(&once).expect("a re-encoded client message decodes");
        assert_eq!(
            encode(&back).unwrap(),
            once,
            "client round trip is idempotent"
        );
    }
    if let Ok(m) = decode_server(data) {
        let once = encode(&m).expect("a decoded server message re-encodes");
        let back = decode_server(&once).expect("a re-encoded server message decodes");
        assert_eq!(
            encode(&back).unwrap(),
            once,
            "server round trip is idempotent"
        );
        if let ServerMsg::Nodes { block, .. } | ServerMsg::Preview { block, .. } = &m {
            check_block(block);
        }
    }
    if let Ok(band) = NearLevelSet::decode(data, 1 << 20) {
        let again = band.encode().expect("a decoded band re-codes");
        assert_eq!(
            NearLevelSet::decode(&again, 1 << 20).expect("a re-coded band decodes"),
            band,
            "band round trip"
        );
    }
    // the same bytes as a block's coded data, straight into the block decoder: the first byte a
    // node count (0..=255), the next a first id (0..=255), the rest the range coder's bytes
    if data.len() >= 2 {
        let mut bytes = data[2..].to_vec();
        bytes.truncate(bytes.len() / 4 * 4);
        check_block(&NodeBlock {
            count: data[0] as u32,
            first: data[1] as u64,
            bytes,
        });
    }
}

/// A block decodes, with each coder, to valid nodes in increasing id order that re-code to the
/// same nodes, or to an error.
fn check_block(block: &NodeBlock) {
    for c in coders() {
        if let Ok(nodes) = c.decode(block) {
            assert_eq!(nodes.len(), block.count as usize);
            for n in &nodes {
                n.validate().expect("decoded nodes are valid");
            }
            assert!(nodes.windows(2).all(|w| w[0].id < w[1].id), "ids increase");
            let again = c.encode(&nodes).expect("decoded nodes re-code");
            assert_eq!(c.decode(&again).unwrap(), nodes, "block round trip");
        }
    }
}

/// Valid frames of every message kind (seeds for mutation).
pub fn seed_frames() -> Vec<Vec<u8>> {
    let node = |id, owned: u8| DetailNode {
        id,
        owned,
        empty_children: 0,
        subtree_max_abs: 0.25,
        coeffs: (0..owned.count_ones())
            .map(|i| i as f32 * 0.5 - 1.0)
            .collect(),
    };
    let client = [
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            token: Some("token".into()),
            have: vec![IdRange { from: 0, to: 10 }, IdRange { from: 20, to: 25 }],
            previewed: vec![IdRange { from: 0, to: 3 }],
        },
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            token: None,
            have: vec![],
            previewed: vec![],
        },
        ClientMsg::View(ViewParams {
            eye: [3.0, 2.0, 1.0],
            target: [0.0; 3],
            up: [0.0, 0.0, 1.0],
            fovy_deg: 40.0,
            width: 512,
            height: 384,
            tol_px: 2.0,
        }),
        ClientMsg::Want(vec![IdRange { from: 7, to: 9 }]),
        ClientMsg::Cancel(vec![IdRange { from: 1, to: 2 }]),
        ClientMsg::Ack { seq: 300 },
    ];
    let server = [
        ServerMsg::Nodes {
            seq: 1,
            block: coders()[0]
                .encode(&[node(0, 0b111111), node(5, 0b000101), node(6, 0)])
                .expect("valid nodes"),
        },
        ServerMsg::Nodes {
            seq: 2,
            block: coders()[1]
                .encode(&[node(0, 0b111111), node(9, 0b000101), node(300, 0)])
                .expect("valid nodes"),
        },
        ServerMsg::Preview {
            seq: 0,
            block: coders()[3]
                .encode(&[node(0, 0b111111), node(5, 0b000101)])
                .expect("valid nodes"),
        },
        // the session's start: the manifest's form, with a preview and a level-set band, and its
        // base mesh as the manifest's named box (short) and as another mesh (whole)
        ServerMsg::Start(Box::new(SessionStart {
            base: {
                let [lo, hi] = session_manifest().bounds;
                let (positions, tets) = tetwave_protocol::shapes::box5(lo, hi);
                tetwave_protocol::BaseMesh {
                    levels: 3,
                    values: vec![0.5; positions.len()],
                    empty: vec![false; tets.len()],
                    predictor: Default::default(),
                    positions,
                    tets,
                }
            },
            manifest: session_manifest(),
        })),
        ServerMsg::Start(Box::new(SessionStart {
            base: one_tet(),
            manifest: session_manifest(),
        })),
        ServerMsg::End { nodes_sent: 1234 },
        ServerMsg::Error {
            code: 401,
            message: "missing or wrong token".into(),
        },
        ServerMsg::Base(Box::new(one_tet())),
        // a box6 base with the axes predictor (its validation checks the Kuhn structure)
        ServerMsg::Base(Box::new({
            let (positions, tets) = tetwave_protocol::shapes::box6([0.0; 3], [1.0; 3]);
            tetwave_protocol::BaseMesh {
                levels: 2,
                values: vec![0.5; positions.len()],
                empty: vec![false; tets.len()],
                predictor: tetwave_protocol::wavelet::Predictor::Axes,
                positions,
                tets,
            }
        })),
    ];
    client
        .iter()
        .map(|m| encode(m).unwrap())
        .chain(server.iter().map(|m| encode(m).unwrap()))
        .collect()
}

/// A session's manifest (with a preview and a level-set band) for seeds.
fn session_manifest() -> tetwave_protocol::store_format::Manifest {
    use tetwave_protocol::store_format::{
        Counts, FileSum, Manifest, Preview, LEVELSET_BAND_FILE, STORE_FORMAT, STORE_VERSION,
    };
    let f = tetwave_protocol::Forest::new(5, 3);
    Manifest {
        format: STORE_FORMAT.into(),
        version: STORE_VERSION,
        dataset: "d".into(),
        source: String::new(),
        bounds: [[0.0; 3], [30.0, 30.0, 0.1]],
        base: "box5".into(),
        base_tets: 5,
        base_vertices: 8,
        levels: 3,
        value_range: [-1.0, 2.0],
        source_value_range: Some([-1.0, 2.5]),
        counts: Counts {
            tets_total: f.total_tets(),
            leaves: f.leaves(),
            nodes: f.nodes(),
            vertices: 729,
            coefficients: 721,
            outside_vertices: 0,
            empty_base_tets: 0,
        },
        encoding: Encoding::uniform(12, 0.01),
        max_error_bound: 0.005,
        max_abs_error: 0.004,
        files: [(
            LEVELSET_BAND_FILE.to_string(),
            FileSum {
                bytes: 1234,
                crc32: 5678,
            },
        )]
        .into_iter()
        .collect(),
        preview: Some(Preview {
            encoding: Encoding::uniform(8, 0.5),
            levels: 2,
            max_error_bound: 0.25,
        }),
        value_histogram: Some(vec![1; tetwave_protocol::store_format::HISTOGRAM_BINS]),
        physical: None,
    }
}

/// A base mesh of one tet for seeds.
fn one_tet() -> tetwave_protocol::BaseMesh {
    tetwave_protocol::BaseMesh {
        levels: 1,
        positions: vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        tets: vec![[0, 1, 2, 3]],
        values: vec![0.0, 1.0, 2.0, 3.0],
        empty: vec![false],
        predictor: Default::default(),
    }
}
