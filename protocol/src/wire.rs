//! Wire frames between server and client: versioned, length-prefixed serde + bincode, with an
//! explicit size limit. Decoding is total: every malformed, truncated, oversized or unknown frame is
//! a [`WireError`], never a panic, and no allocation exceeds [`MAX_FRAME_BYTES`].
//!
//! Frame layout: `u32 LE payload length | u16 LE protocol version | payload (bincode, standard
//! config)`; the length counts the version and payload bytes. Over WebSocket, one binary message
//! carries exactly one frame.

use crate::block::{NodeBlock, MAX_BLOCK_NODES};
use crate::{BaseMesh, TetId};
use serde::{Deserialize, Serialize};

mod manifest;
mod start;
pub use start::SessionStart;

/// 2: `Nodes` carries a coded [`NodeBlock`] (version 1 sent f32 detail nodes). 3: the blocks of
/// store format 3. 4: the manifest carries `source_value_range` (bincode is positional: a
/// version-3 peer would misread it). 5: the blocks of store format 4 (lossless coefficients
/// coded). 6: the base mesh and blocks of store format 5 (positions as f32
/// where exact, modelled signs). 7: the base mesh names its predictor (store format 6). 8: the
/// blocks of store format 7 (no subtree bound on the finest node level, ids as runs and jumps by
/// sibling group). 9: the session's manifest in its own form (`manifest`, with the store's
/// preview if any), the base mesh as store format 8 writes it (a named box as its two corners),
/// `Preview` batches, `Hello.previewed`. 10: `Hello.previewed` names the preview nodes held (a
/// cut preview resumes where it stopped); the session starts with one `Start` frame, the manifest
/// and the base mesh, a named box's corners once (`start`). 12: the manifest carries the
/// volume file's world (`physical`: origin, frame, units).
pub const PROTOCOL_VERSION: u16 = 12;
/// Largest frame (length prefix excluded) either side sends or accepts.
pub const MAX_FRAME_BYTES: usize = 64 << 20;
/// Most id ranges one message may carry.
pub const MAX_RANGES: usize = 1 << 16;

/// A half-open range of node ids `[from, to)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct IdRange {
    pub from: TetId,
    pub to: TetId,
}

/// The client's camera, for view-dependent ordering on the server.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ViewParams {
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fovy_deg: f64,
    pub width: u32,
    pub height: u32,
    /// Screen-space tolerance in pixels.
    pub tol_px: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ClientMsg {
    /// First message. `have`: node ranges the client already holds (resume after a drop);
    /// `previewed`: the preview nodes it holds (a connection dropped before the store's nodes
    /// came): the preview resumes without them.
    Hello {
        version: u16,
        token: Option<String>,
        have: Vec<IdRange>,
        previewed: Vec<IdRange>,
    },
    /// The camera moved: the server re-prioritises what it has not sent yet.
    View(ViewParams),
    /// Send these nodes (again), e.g. after a gap.
    Want(Vec<IdRange>),
    /// Do not send these nodes.
    Cancel(Vec<IdRange>),
    /// Batches up to `seq` were received (flow control).
    Ack { seq: u64 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ServerMsg {
    /// A session's first message: the store's manifest, as much of it as a client needs
    /// (`manifest`), and the base mesh (`start`).
    Start(#[serde(with = "start")] Box<SessionStart>),
    /// The base mesh alone (`GET /v1/base`).
    Base(Box<BaseMesh>),
    /// Detail nodes as one coded block ([`crate::block`]; decode with the
    /// [`crate::block::BlockCoder`] of the manifest and base mesh); `seq` increases by one per batch
    /// on a connection.
    Nodes {
        seq: u64,
        block: NodeBlock,
    },
    /// Everything the client did not already have has been sent.
    End {
        nodes_sent: u64,
    },
    Error {
        code: u16,
        message: String,
    },
    /// Preview nodes ([`crate::store_format::Preview`]) as one coded block (decode with the
    /// [`crate::block::BlockCoder`] of the preview's encoding and the base mesh). A new session
    /// may get some before its `Nodes`; the store's own node replaces each later. `seq` counts
    /// with the `Nodes` batches'.
    Preview {
        seq: u64,
        block: NodeBlock,
    },
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WireError {
    #[error("frame truncated: need {need} bytes, have {have}")]
    Truncated { need: usize, have: usize },
    #[error("frame of {len} bytes exceeds the {MAX_FRAME_BYTES}-byte limit")]
    Oversized { len: usize },
    #[error("protocol version {got}, expected {PROTOCOL_VERSION}")]
    Version { got: u16 },
    #[error("malformed frame: {0}")]
    Malformed(String),
    #[error("{0} trailing bytes after the message")]
    Trailing(usize),
    #[error("invalid message: {0}")]
    Invalid(String),
}

fn config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_FRAME_BYTES>()
}

/// Encodes one frame. Fails only if the message exceeds [`MAX_FRAME_BYTES`].
pub fn encode<T: Serialize>(msg: &T) -> Result<Vec<u8>, WireError> {
    let payload = bincode::serde::encode_to_vec(msg, config())
        .map_err(|e| WireError::Malformed(e.to_string()))?;
    let len = payload.len() + 2;
    if len > MAX_FRAME_BYTES {
        return Err(WireError::Oversized { len });
    }
    let mut out = Vec::with_capacity(4 + len);
    out.extend_from_slice(&(len as u32).to_le_bytes());
    out.extend_from_slice(&PROTOCOL_VERSION.to_le_bytes());
    out.extend_from_slice(&payload);
    Ok(out)
}

/// Length of the first complete frame in `buf` (prefix included), `Ok(None)` if more bytes are
/// needed; an error if the prefix announces an oversized frame (a stream reader can stop at once).
pub fn frame_len(buf: &[u8]) -> Result<Option<usize>, WireError> {
    if buf.len() < 4 {
        return Ok(None);
    }
    let len = u32::from_le_bytes([buf[0], buf[1], buf[2], buf[3]]) as usize;
    if len > MAX_FRAME_BYTES {
        return Err(WireError::Oversized { len });
    }
    Ok((buf.len() >= 4 + len).then_some(4 + len))
}

fn decode<T: for<'de> Deserialize<'de>>(frame: &[u8]) -> Result<T, WireError> {
    if frame.len() < 6 {
        return Err(WireError::Truncated {
            need: 6,
            have: frame.len(),
        });
    }
    let len = u32::from_le_bytes([frame[0], frame[1], frame[2], frame[3]]) as usize;
    if len > MAX_FRAME_BYTES {
        return Err(WireError::Oversized { len });
    }
    if len < 2 || frame.len() < 4 + len {
        return Err(WireError::Truncated {
            need: 4 + len.max(2),
            have: frame.len(),
        });
    }
    if frame.len() > 4 + len {
        return Err(WireError::Trailing(frame.len() - 4 - len));
    }
    let version = u16::from_le_bytes([frame[4], frame[5]]);
    if version != PROTOCOL_VERSION {
        return Err(WireError::Version { got: version });
    }
    let (msg, used): (T, usize) = bincode::serde::decode_from_slice(&frame[6..], config())
        .map_err(|e| WireError::Malformed(e.to_string()))?;
    if used != len - 2 {
        return Err(WireError::Trailing(len - 2 - used));
    }
    Ok(msg)
}

fn check_ranges(r: &[IdRange]) -> Result<(), WireError> {
    if r.len() > MAX_RANGES {
        return Err(WireError::Invalid(format!(
            "{} ranges (limit {MAX_RANGES})",
            r.len()
        )));
    }
    if r.iter().any(|x| x.from > x.to) {
        return Err(WireError::Invalid("a range ends before it starts".into()));
    }
    Ok(())
}

/// Decodes and validates one client frame (ranges well formed, view finite and sized).
pub fn decode_client(frame: &[u8]) -> Result<ClientMsg, WireError> {
    let msg: ClientMsg = decode(frame)?;
    match &msg {
        ClientMsg::Hello {
            have, previewed, ..
        } => {
            check_ranges(have)?;
            check_ranges(previewed)?
        }
        ClientMsg::Want(r) | ClientMsg::Cancel(r) => check_ranges(r)?,
        ClientMsg::View(v) => {
            let finite = v
                .eye
                .iter()
                .chain(&v.target)
                .chain(&v.up)
                .all(|x| x.is_finite())
                && v.fovy_deg.is_finite()
                && v.tol_px.is_finite();
            if !finite
                || !(1.0..179.0).contains(&v.fovy_deg)
                || v.width == 0
                || v.height == 0
                || v.width > 16384
                || v.height > 16384
                || v.tol_px < 0.0
            {
                return Err(WireError::Invalid("view parameters out of range".into()));
            }
        }
        ClientMsg::Ack { .. } => {}
    }
    Ok(msg)
}

/// Decodes and validates one server frame (base mesh structurally valid, a block's node count
/// within [`MAX_BLOCK_NODES`]; the block's content is checked when it is decoded).
pub fn decode_server(frame: &[u8]) -> Result<ServerMsg, WireError> {
    let msg: ServerMsg = decode(frame)?;
    match &msg {
        ServerMsg::Nodes { block, .. } | ServerMsg::Preview { block, .. }
            if block.count > MAX_BLOCK_NODES =>
        {
            return Err(WireError::Invalid(format!(
                "block of {} nodes (limit {MAX_BLOCK_NODES})",
                block.count
            )));
        }
        ServerMsg::Base(b) => b
            .validate()
            .map_err(|e| WireError::Invalid(e.to_string()))?,
        ServerMsg::Start(st) => st
            .base
            .validate()
            .map_err(|e| WireError::Invalid(e.to_string()))?,
        _ => {}
    }
    Ok(msg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store_format::{Counts, Encoding, Manifest};
    use proptest::prelude::*;

    fn hello() -> ClientMsg {
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            token: Some("t".into()),
            have: vec![IdRange { from: 0, to: 5 }],
            previewed: vec![IdRange { from: 5, to: 9 }],
        }
    }

    #[test]
    fn round_trip() {
        let msgs = [
            hello(),
            ClientMsg::Want(vec![IdRange { from: 3, to: 9 }]),
            ClientMsg::Ack { seq: 7 },
            ClientMsg::View(ViewParams {
                eye: [1.0, 2.0, 3.0],
                target: [0.0; 3],
                up: [0.0, 0.0, 1.0],
                fovy_deg: 40.0,
                width: 512,
                height: 512,
                tol_px: 2.0,
            }),
        ];
        for m in msgs {
            assert_eq!(decode_client(&encode(&m).unwrap()).unwrap(), m);
        }
        let n = ServerMsg::Nodes {
            seq: 1,
            block: NodeBlock {
                count: 2,
                first: 4,
                bytes: vec![1, 2, 3, 4],
            },
        };
        assert_eq!(decode_server(&encode(&n).unwrap()).unwrap(), n);
        // the manifest (with both encodings) travels in bincode too, in the session's form
        for encoding in [Encoding::F32, Encoding::uniform(12, 0.25)] {
            let mut m = Manifest {
                format: "tetwave-store".into(),
                version: crate::store_format::STORE_VERSION,
                dataset: "d".into(),
                source: String::new(),
                bounds: [[0.0; 3], [1.0; 3]],
                base: "box5".into(),
                base_tets: 5,
                base_vertices: 8,
                levels: 2,
                value_range: [0.0, 1.0],
                source_value_range: Some([-0.5, 1.5]),
                counts: Counts {
                    tets_total: 365,
                    leaves: 320,
                    nodes: 45,
                    vertices: 35,
                    coefficients: 27,
                    outside_vertices: 0,
                    empty_base_tets: 0,
                },
                encoding,
                max_error_bound: 1e-6,
                max_abs_error: 0.0,
                files: Default::default(),
                preview: None,
                value_histogram: None,
                physical: None,
            };
            let (positions, tets) = crate::shapes::box5([0.0; 3], [1.0; 3]);
            let base = BaseMesh {
                levels: 2,
                values: vec![0.5; positions.len()],
                empty: vec![false; tets.len()],
                positions,
                tets,
                predictor: crate::wavelet::Predictor::Parent,
            };
            let start = |manifest: &Manifest| {
                ServerMsg::Start(Box::new(SessionStart {
                    manifest: manifest.clone(),
                    base: base.clone(),
                }))
            };
            let sent = start(&m);
            assert_eq!(decode_server(&encode(&sent).unwrap()).unwrap(), sent);
            // what the session leaves out (manifest::tests and start::tests cover the rest)
            m.source = "input.vtu".into();
            let got = decode_server(&encode(&start(&m)).unwrap()).unwrap();
            assert_eq!(got, sent);
        }
    }

    #[test]
    fn bad_frames_are_errors() {
        let good = encode(&hello()).unwrap();
        // truncated at every length
        for cut in 0..good.len() {
            assert!(decode_client(&good[..cut]).is_err());
        }
        // trailing bytes
        let mut t = good.clone();
        t.push(0);
        assert!(matches!(decode_client(&t), Err(WireError::Trailing(_))));
        // oversized length prefix: rejected before any allocation
        let mut big = good.clone();
        big[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            decode_client(&big),
            Err(WireError::Oversized { .. })
        ));
        assert!(matches!(frame_len(&big), Err(WireError::Oversized { .. })));
        // wrong version
        let mut v = good.clone();
        v[4] = 99;
        assert!(matches!(
            decode_client(&v),
            Err(WireError::Version { got: 99 })
        ));
        // unknown message kind (enum tag beyond the variants)
        let mut k = good.clone();
        k[6] = 200;
        assert!(matches!(decode_client(&k), Err(WireError::Malformed(_))));
        // a block declaring more nodes than a block may hold
        let bad = ServerMsg::Nodes {
            seq: 0,
            block: NodeBlock {
                count: MAX_BLOCK_NODES + 1,
                first: 0,
                bytes: vec![],
            },
        };
        assert!(matches!(
            decode_server(&encode(&bad).unwrap()),
            Err(WireError::Invalid(_))
        ));
        // a range that ends before it starts
        let r = ClientMsg::Want(vec![IdRange { from: 9, to: 3 }]);
        assert!(matches!(
            decode_client(&encode(&r).unwrap()),
            Err(WireError::Invalid(_))
        ));
    }

    #[test]
    fn huge_inner_length_does_not_allocate() {
        // a Nodes frame claiming 2^60 coded bytes inside a small frame
        let mut f = encode(&ServerMsg::Nodes {
            seq: 0,
            block: NodeBlock {
                count: 0,
                first: 0,
                bytes: vec![],
            },
        })
        .unwrap();
        // payload: variant tag (2), seq (0), count (0), first (0), then the bytes' length varint:
        // replace it with a huge u64
        f.truncate(6 + 4);
        f.push(0xfd); // bincode varint marker for u64
        f.extend_from_slice(&(1u64 << 60).to_le_bytes());
        let len = (f.len() - 4) as u32;
        f[..4].copy_from_slice(&len.to_le_bytes());
        assert!(decode_server(&f).is_err());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        /// Decoding never panics, whatever the bytes.
        #[test]
        fn decoders_are_total(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode_client(&bytes);
            let _ = decode_server(&bytes);
            let _ = frame_len(&bytes);
        }

        /// Decoding never panics on a valid frame with random bytes flipped.
        #[test]
        fn mutated_frames_are_total(flips in prop::collection::vec((any::<usize>(), any::<u8>()), 1..8)) {
            let mut f = encode(&hello()).unwrap();
            for (i, b) in flips {
                let n = f.len();
                f[i % n] ^= b;
            }
            let _ = decode_client(&f);
            let _ = decode_server(&f);
        }
    }
}
