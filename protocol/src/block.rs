//! Coded blocks of detail nodes: what a `Nodes` frame carries and `/v1/nodes` serves.
//!
//! A block is any set of nodes (the server's batch, an id range), entropy-coded on its own
//! ([`crate::entropy`]: fresh adaptive models per block), so blocks can be sent and applied in any
//! order. Per node it codes only what the client cannot derive:
//!
//! - **ids**: increasing; the first in the header, then each against the previous one (a flag
//!   for the next id, else a jump in whole sibling groups or in ids, see `Ids`: runs and the
//!   whole groups view order sends cost almost nothing);
//! - **owned mask**: derived from the hierarchy ([`crate::ownership`]); one adaptive flag says
//!   whether the node's mask differs, and only then are its 6 bits sent;
//! - **empty children**: an adaptive flag, then the 8 bits where any child is empty;
//! - **subtree bound** (`subtree_max_abs`, one value for a group of siblings, see
//!   [`DetailNode::subtree_max_abs`]): for quantized stores a class `k`, the smallest with
//!   `(2^k − 1) · step` (the node level's step, [`crate::wavelet::LevelSteps`]) at least the
//!   bound and at least the node's own code magnitudes; the
//!   decoded bound is `(2^k − 1) · step`, an upper bound within a factor 2, which is the safe side
//!   for the selection's error estimate. A node that follows its sibling in the block sends one
//!   adaptive flag when its class is the sibling's (so a group costs about one class). Lossless
//!   stores round the bound up to a power of two (within a factor 2, the same safe side) and code
//!   its exponent the same way ([`pow2_class`]). Nodes of the finest node level (7/8 of all) send
//!   no bound: it would cost more than their coefficients tell, and their parent's covers them
//!   ([`crate::node::INHERITED_BOUND`]). Their codes are coded under one model of their own, with
//!   the quantizer's code length as the limit;
//! - **coefficients**: quantized codes by magnitude under the class `k` (none at all when `k = 0`:
//!   a zero subtree costs only its class), each nonzero code's sign by an adaptive bit whose context
//!   is the node's two previous nonzero signs. Lossless stores keep every bit of the
//!   f32: its sign raw, its exponent as the difference to the previous coefficient's, how many
//!   mantissa bits lie above the lowest set one (modelled by exponent: a detail `f(m) − P(m)` of
//!   two values of one binade is a multiple of their ulp, so its low bits are zero), and those
//!   bits raw.
//!
//! Decoding is total: malformed, truncated or oversized blocks are [`BlockError`]s, and the work
//! is bounded by the node count the header declares (at most [`MAX_BLOCK_NODES`]).

use crate::entropy::{unzigzag, zigzag, Bit, Decoder, Encoder, EntropyError, Floats, UInt};
use crate::hierarchy::Forest;
use crate::node::INHERITED_BOUND;
use crate::ownership::Ownership;
use crate::store_format::Encoding;
use crate::wavelet::Quantizer;
use crate::{BaseMesh, DetailNode, TetId};
use serde::{Deserialize, Serialize};

/// Most nodes one block may hold.
pub const MAX_BLOCK_NODES: u32 = 1 << 16;
/// Largest subtree class (bit length of a code magnitude).
const MAX_CLASS: u32 = 40;
/// Largest lossless subtree class ([`pow2_class`] of `f32::MAX`).
const MAX_POW2_CLASS: u32 = 278;

/// A coded set of detail nodes (see the module documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NodeBlock {
    /// Nodes in the block.
    pub count: u32,
    /// The lowest id (0 when empty).
    pub first: TetId,
    /// The range coder's output.
    pub bytes: Vec<u8>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BlockError {
    #[error("block of {0} nodes exceeds the {MAX_BLOCK_NODES}-node limit")]
    TooManyNodes(u64),
    #[error("node id {id} is outside the hierarchy's {nodes} nodes")]
    IdOutOfRange { id: TetId, nodes: u64 },
    #[error("node {0} appears twice in one block")]
    Duplicate(TetId),
    #[error("node {id}: {reason}")]
    BadNode { id: TetId, reason: String },
    #[error("coded block: {0}")]
    Coding(#[from] EntropyError),
}

/// How one node's coefficients are coded ([`BlockCoder::coefficients_of`]).
#[derive(Debug, Clone, Copy)]
enum Coefficients {
    /// f32 bits as stored.
    Raw,
    Quantized(Quantizer),
}

/// Codes and decodes blocks of one store (its hierarchy and coefficient encoding).
#[derive(Debug, Clone)]
pub struct BlockCoder {
    forest: Forest,
    /// Nodes in the hierarchy; 0 when its count does not fit in u64 (then no block decodes: such a
    /// base mesh is refused anyway, and no id arithmetic may overflow).
    total: u64,
    ownership: Ownership,
    /// A quantized store's quantizers, indexed by levels above the finest
    /// ([`crate::wavelet::LevelSteps::quantizers`]); `None`: lossless.
    quantizers: Option<Vec<Quantizer>>,
    /// Ids from here on are finest-level nodes, whose subtree bound is not coded
    /// ([`INHERITED_BOUND`]); `u64::MAX` when there are none.
    finest: u64,
}

/// Every adaptive model of one block.
struct Models {
    /// The ids after the first ([`Ids`]).
    ids: Ids,
    mask_differs: [Bit; 9],
    empty_any: Bit,
    empty_bits: [Bit; 8],
    class: Vec<UInt>,
    same_class: Bit,
    /// Code magnitudes, by subtree class; the last one for finest-level nodes (no class).
    magnitude: Vec<UInt>,
    /// Signs, by the node's two previous nonzero signs ([`NodeSigns`]).
    sign: [Bit; 9],
    /// Lossless: the subtree class's difference to the previous one (zigzag).
    class_delta: UInt,
    /// Lossless: the coefficients' f32s.
    floats: Floats,
}

impl Models {
    fn new() -> Self {
        Models {
            ids: Ids::default(),
            mask_differs: [Bit::default(); 9],
            empty_any: Bit::default(),
            empty_bits: [Bit::default(); 8],
            class: vec![UInt::default(); 16],
            same_class: Bit::default(),
            magnitude: vec![UInt::default(); FINEST_MAGNITUDES + 1],
            sign: [Bit::default(); 9],
            class_delta: UInt::default(),
            floats: Floats::default(),
        }
    }
}

impl BlockCoder {
    pub fn new(base: &BaseMesh, encoding: &Encoding) -> Self {
        let forest = base.forest();
        BlockCoder {
            forest,
            total: forest.checked_nodes().unwrap_or(0),
            ownership: Ownership::new(base),
            quantizers: encoding
                .quantizer()
                .map(|(q, steps)| steps.quantizers(q, forest.levels)),
            finest: forest.checked_finest_nodes_start().unwrap_or(u64::MAX),
        }
    }

    /// The coder of a store's preview ([`crate::store_format::Preview`], with its encoding): no
    /// node codes a subtree bound, as on the finest node level (a preview node's decodes as
    /// [`INHERITED_BOUND`]; the store's own node brings the bound), and every node's codes take
    /// that level's magnitude model.
    pub fn for_preview(base: &BaseMesh, encoding: &Encoding) -> Self {
        BlockCoder {
            finest: 0,
            ..Self::new(base, encoding)
        }
    }

    /// How node `id` (an id within the hierarchy: callers check it) has its coefficients coded:
    /// a quantized store's with its level's quantizer.
    fn coefficients_of(&self, id: TetId) -> Coefficients {
        match &self.quantizers {
            None => Coefficients::Raw,
            Some(qs) => {
                let above = self.forest.levels - 1 - self.forest.level(id);
                Coefficients::Quantized(qs[above as usize])
            }
        }
    }

    /// Whether `id` and `prev` have the same parent (base tets have none).
    fn siblings(&self, prev: Option<TetId>, id: TetId) -> bool {
        match (
            prev.and_then(|p| self.forest.parent(p)),
            self.forest.parent(id),
        ) {
            (Some(a), Some(b)) => a == b,
            _ => false,
        }
    }

    fn child_context(&self, id: TetId) -> usize {
        self.forest.child_index(id).map_or(8, |c| c)
    }

    /// Codes `nodes` (any order; ids distinct and within the hierarchy).
    pub fn encode(&self, nodes: &[DetailNode]) -> Result<NodeBlock, BlockError> {
        if nodes.len() as u64 > MAX_BLOCK_NODES as u64 {
            return Err(BlockError::TooManyNodes(nodes.len() as u64));
        }
        let total = self.total;
        let mut order: Vec<&DetailNode> = nodes.iter().collect();
        order.sort_unstable_by_key(|n| n.id);
        for w in order.windows(2) {
            if w[0].id == w[1].id {
                return Err(BlockError::Duplicate(w[0].id));
            }
        }
        let mut e = Encoder::default();
        let mut m = Models::new();
        let mut prev: Option<TetId> = None;
        let mut prev_class = 0u32;
        for n in &order {
            if n.id >= total {
                return Err(BlockError::IdOutOfRange {
                    id: n.id,
                    nodes: total,
                });
            }
            n.validate().map_err(|err| BlockError::BadNode {
                id: n.id,
                reason: err.to_string(),
            })?;
            if let Some(p) = prev {
                m.ids.encode(&mut e, self.forest, p, n.id)?;
            }
            let after_sibling = self.siblings(prev, n.id);
            prev = Some(n.id);
            let derived = self.ownership.owned(n.id);
            let cc = self.child_context(n.id);
            e.bit(&mut m.mask_differs[cc], n.owned != derived);
            if n.owned != derived {
                e.raw(n.owned as u64, 6);
            }
            e.bit(&mut m.empty_any, n.empty_children != 0);
            if n.empty_children != 0 {
                for (i, b) in m.empty_bits.iter_mut().enumerate() {
                    e.bit(b, n.empty_children >> i & 1 == 1);
                }
            }
            let finest = n.id >= self.finest;
            match self.coefficients_of(n.id) {
                Coefficients::Raw if finest => {
                    for &c in &n.coeffs {
                        e.float(&mut m.floats, c)?;
                    }
                }
                Coefficients::Raw => {
                    let class = pow2_class(n.subtree_max_abs);
                    let same = after_sibling && class == prev_class;
                    if after_sibling {
                        e.bit(&mut m.same_class, same);
                    }
                    if !same {
                        e.uint(&mut m.class_delta, zigzag(class as i64 - prev_class as i64))?;
                    }
                    prev_class = class;
                    for &c in &n.coeffs {
                        e.float(&mut m.floats, c)?;
                    }
                }
                Coefficients::Quantized(q) if finest => {
                    encode_codes(
                        &mut e,
                        (&mut m.magnitude[FINEST_MAGNITUDES], &mut m.sign),
                        n.coeffs.iter().map(|&c| q.encode(c)),
                        code_bits(q),
                    )?;
                }
                Coefficients::Quantized(q) => {
                    let codes: Vec<i32> = n.coeffs.iter().map(|&c| q.encode(c)).collect();
                    // the smallest class whose decoded bound covers the subtree max and whose
                    // magnitudes cover the node's own codes (so a decoded node re-codes to the
                    // same class)
                    let own = codes.iter().map(|c| c.unsigned_abs()).max().unwrap_or(0);
                    let min_class = u32::BITS - own.leading_zeros();
                    let class = (min_class..=MAX_CLASS)
                        .find(|&k| {
                            let b = class_bound(k, q.step);
                            b.is_finite() && b >= n.subtree_max_abs
                        })
                        .ok_or_else(|| BlockError::BadNode {
                            id: n.id,
                            reason: format!(
                                "subtree max {} is beyond {MAX_CLASS} bits of step {}",
                                n.subtree_max_abs, q.step
                            ),
                        })?;
                    let same = after_sibling && class == prev_class;
                    if after_sibling {
                        e.bit(&mut m.same_class, same);
                    }
                    if !same {
                        e.uint(&mut m.class[prev_class.min(15) as usize], class as u64)?;
                    }
                    prev_class = class;
                    if class > 0 {
                        // a class-k magnitude has at most k bits
                        encode_codes(
                            &mut e,
                            (&mut m.magnitude[class as usize], &mut m.sign),
                            codes.iter().copied(),
                            class,
                        )?;
                    }
                }
            }
        }
        Ok(NodeBlock {
            count: order.len() as u32,
            first: order.first().map_or(0, |n| n.id),
            bytes: e.finish(),
        })
    }

    /// Decodes a block into its nodes, in increasing id order, each passing
    /// [`DetailNode::validate`].
    pub fn decode(&self, block: &NodeBlock) -> Result<Vec<DetailNode>, BlockError> {
        if block.count > MAX_BLOCK_NODES {
            return Err(BlockError::TooManyNodes(block.count as u64));
        }
        let total = self.total;
        let mut out = Vec::with_capacity(block.count as usize);
        if block.count == 0 {
            return Ok(out);
        }
        let mut d = Decoder::new(&block.bytes)?;
        let mut m = Models::new();
        let mut id = block.first;
        let mut prev: Option<TetId> = None;
        let mut prev_class = 0u32;
        for i in 0..block.count {
            if i > 0 {
                id = m
                    .ids
                    .decode(&mut d, self.forest, id)?
                    .ok_or(BlockError::IdOutOfRange { id, nodes: total })?;
            }
            if id >= total {
                return Err(BlockError::IdOutOfRange { id, nodes: total });
            }
            let after_sibling = self.siblings(prev, id);
            prev = Some(id);
            let cc = self.child_context(id);
            let owned = if d.bit(&mut m.mask_differs[cc])? {
                d.raw(6)? as u8
            } else {
                self.ownership.owned(id)
            };
            let empty_children = if d.bit(&mut m.empty_any)? {
                let mut v = 0u8;
                for (i, b) in m.empty_bits.iter_mut().enumerate() {
                    v |= (d.bit(b)? as u8) << i;
                }
                v
            } else {
                0
            };
            let n_coeffs = owned.count_ones() as usize;
            let finest = id >= self.finest;
            let (subtree_max_abs, coeffs) = match self.coefficients_of(id) {
                Coefficients::Raw if finest => {
                    let coeffs = (0..n_coeffs)
                        .map(|_| d.float(&mut m.floats))
                        .collect::<Result<Vec<_>, _>>()?;
                    (INHERITED_BOUND, coeffs)
                }
                Coefficients::Quantized(q) if finest => {
                    let limit = Quantizer::max_code(q.bits) as u64;
                    let coeffs = decode_codes(
                        &mut d,
                        (&mut m.magnitude[FINEST_MAGNITUDES], &mut m.sign),
                        (n_coeffs, code_bits(q), limit),
                        q,
                    )?
                    .map_err(|mag| BlockError::BadNode {
                        id,
                        reason: format!("code {mag} exceeds the quantizer's {limit}"),
                    })?;
                    (INHERITED_BOUND, coeffs)
                }
                Coefficients::Raw => {
                    let same = after_sibling && d.bit(&mut m.same_class)?;
                    let class = if same {
                        prev_class as i64
                    } else {
                        prev_class as i64 + unzigzag(d.uint(&mut m.class_delta)?)
                    };
                    if !(0..=MAX_POW2_CLASS as i64).contains(&class) {
                        return Err(BlockError::BadNode {
                            id,
                            reason: format!(
                                "subtree class {class} is outside 0..={MAX_POW2_CLASS}"
                            ),
                        });
                    }
                    prev_class = class as u32;
                    let coeffs = (0..n_coeffs)
                        .map(|_| d.float(&mut m.floats))
                        .collect::<Result<Vec<_>, _>>()?;
                    (pow2_bound(prev_class), coeffs)
                }
                Coefficients::Quantized(q) => {
                    let same = after_sibling && d.bit(&mut m.same_class)?;
                    let class = if same {
                        prev_class as u64
                    } else {
                        d.uint(&mut m.class[prev_class.min(15) as usize])?
                    };
                    if class > MAX_CLASS as u64 {
                        return Err(BlockError::BadNode {
                            id,
                            reason: format!("subtree class {class} exceeds {MAX_CLASS}"),
                        });
                    }
                    let class = class as u32;
                    prev_class = class;
                    let mut coeffs = vec![0f32; n_coeffs];
                    if class > 0 {
                        let limit = ((1u64 << class) - 1).min(Quantizer::max_code(q.bits) as u64);
                        coeffs = decode_codes(
                            &mut d,
                            (&mut m.magnitude[class as usize], &mut m.sign),
                            (n_coeffs, class, limit),
                            q,
                        )?
                        .map_err(|mag| BlockError::BadNode {
                            id,
                            reason: format!("code {mag} exceeds its class {class}"),
                        })?;
                    }
                    (class_bound(class, q.step), coeffs)
                }
            };
            let node = DetailNode {
                id,
                owned,
                empty_children,
                subtree_max_abs,
                coeffs,
            };
            node.validate().map_err(|err| BlockError::BadNode {
                id,
                reason: err.to_string(),
            })?;
            if !finest && !node.subtree_max_abs.is_finite() {
                // a class beyond what the step allows (a block coded for another quantizer)
                return Err(BlockError::BadNode {
                    id,
                    reason: "subtree bound overflows f32".into(),
                });
            }
            if node.subtree_max_abs.is_nan() || node.subtree_max_abs < 0.0 {
                return Err(BlockError::BadNode {
                    id,
                    reason: "negative subtree bound".into(),
                });
            }
            out.push(node);
        }
        Ok(out)
    }
}

/// A node's quantized codes: each magnitude (`models.0`, at most `max_bits` bits) and, when not
/// zero, its sign (`models.1`, by the node's previous signs, [`NodeSigns`]).
fn encode_codes(
    e: &mut Encoder,
    models: (&mut UInt, &mut [Bit; 9]),
    codes: impl Iterator<Item = i32>,
    max_bits: u32,
) -> Result<(), EntropyError> {
    let (magnitude, sign) = models;
    let mut signs = NodeSigns::default();
    for c in codes {
        e.uint_within(magnitude, c.unsigned_abs() as u64, max_bits)?;
        if c != 0 {
            e.bit(&mut sign[signs.context()], c < 0);
        }
        signs.push(c);
    }
    Ok(())
}

/// Reads what [`encode_codes`] wrote: `count` codes of at most `max_bits` bits, as coefficients of
/// `q`; the inner error is a magnitude beyond `limit`.
fn decode_codes(
    d: &mut Decoder,
    models: (&mut UInt, &mut [Bit; 9]),
    (count, max_bits, limit): (usize, u32, u64),
    q: Quantizer,
) -> Result<Result<Vec<f32>, u64>, EntropyError> {
    let (magnitude, sign) = models;
    let mut signs = NodeSigns::default();
    let mut out = Vec::with_capacity(count);
    for _ in 0..count {
        let mag = d.uint_within(magnitude, max_bits)?;
        if mag > limit {
            return Ok(Err(mag));
        }
        let negative = mag != 0 && d.bit(&mut sign[signs.context()])?;
        let code = if negative { -(mag as i32) } else { mag as i32 };
        signs.push(code);
        out.push(q.decode(code));
    }
    Ok(Ok(out))
}

/// A node's signs so far, the context of its next one: the residuals of one refinement share the
/// field's local third derivative, so their signs go together (bench-rd's quantized stores are
/// 1–3 % smaller than with raw sign bits; the same kind of context for magnitudes cost more in
/// diluted statistics than it saved).
#[derive(Default)]
struct NodeSigns {
    /// The last two nonzero signs, 0 none, 1 +, 2 − (older × 3 + newer).
    last: usize,
}

impl NodeSigns {
    fn context(&self) -> usize {
        self.last
    }
    fn push(&mut self, code: i32) {
        if code != 0 {
            self.last = self.last % 3 * 3 + 1 + (code < 0) as usize;
        }
    }
}

/// The magnitude model of finest-level nodes' codes (after the classes' `0..=MAX_CLASS`).
const FINEST_MAGNITUDES: usize = MAX_CLASS as usize + 1;

/// Bit length of the largest code magnitude of `q` ([`Quantizer::max_code`]).
fn code_bits(q: Quantizer) -> u32 {
    (q.bits as u32).saturating_sub(1)
}

/// Gap contexts: the previous jump's bit length, 0..=11 (longer ones share the last).
const GAP_CONTEXTS: usize = 12;

fn gap_context(gap: u64) -> usize {
    ((u64::BITS - gap.leading_zeros()) as usize).min(GAP_CONTEXTS - 1)
}

/// The models of a block's ids after the first, each coded against the previous one `p`:
///
/// - one adaptive flag "is `p + 1`" (context: whether `p` ends its sibling group): a batch of
///   whole sibling groups is mostly runs, and a group's end is where a run breaks;
/// - else a flag "starts a sibling group", then the number of whole groups skipped since `p`'s
///   (an adaptive integer): view order sends groups, and a jump to one costs no bits for its
///   position inside a group;
/// - else the gap `id − p − 2` (an adaptive integer).
///
/// The integers' context is the previous jump's bit length.
struct Ids {
    next: [Bit; 2],
    group_start: Bit,
    groups: Vec<UInt>,
    gap: Vec<UInt>,
    ctx: usize,
}

impl Default for Ids {
    fn default() -> Self {
        Ids {
            next: [Bit::default(); 2],
            group_start: Bit::default(),
            groups: vec![UInt::default(); GAP_CONTEXTS],
            gap: vec![UInt::default(); GAP_CONTEXTS],
            ctx: 0,
        }
    }
}

impl Ids {
    /// 1 when `p` ends its sibling group, else 0.
    fn next_context(forest: Forest, p: TetId) -> usize {
        (forest.child_index(p) == Some(7)) as usize
    }

    /// The model of the next jump: in groups or in ids, by the previous jump's length.
    fn jump_model(&mut self, starts: bool) -> &mut UInt {
        let models = if starts {
            &mut self.groups
        } else {
            &mut self.gap
        };
        &mut models[self.ctx]
    }

    /// The first sibling group a jump from `p` to a group start may land in: the one after `p`'s
    /// (the first group when `p` is a base tet).
    fn first_group_after(forest: Forest, p: TetId) -> u64 {
        if p < forest.n_base {
            0
        } else {
            (p - forest.n_base) / 8 + 1
        }
    }

    fn encode(
        &mut self,
        e: &mut Encoder,
        forest: Forest,
        p: TetId,
        id: TetId,
    ) -> Result<(), EntropyError> {
        e.bit(&mut self.next[Self::next_context(forest, p)], id == p + 1);
        if id == p + 1 {
            return Ok(());
        }
        let starts = forest.child_index(id) == Some(0);
        e.bit(&mut self.group_start, starts);
        let jump = if starts {
            (id - forest.n_base) / 8 - Self::first_group_after(forest, p)
        } else {
            id - p - 2
        };
        e.uint(self.jump_model(starts), jump)?;
        self.ctx = gap_context(jump);
        Ok(())
    }

    /// The id after `p`; `None` when it would overflow.
    fn decode(
        &mut self,
        d: &mut Decoder,
        forest: Forest,
        p: TetId,
    ) -> Result<Option<TetId>, EntropyError> {
        if d.bit(&mut self.next[Self::next_context(forest, p)])? {
            return Ok(p.checked_add(1));
        }
        let starts = d.bit(&mut self.group_start)?;
        let jump = d.uint(self.jump_model(starts))?;
        self.ctx = gap_context(jump);
        Ok(if starts {
            Self::first_group_after(forest, p)
                .checked_add(jump)
                .and_then(|g| g.checked_mul(8))
                .and_then(|x| x.checked_add(forest.n_base))
        } else {
            p.checked_add(jump).and_then(|x| x.checked_add(2))
        })
    }
}

/// A lossless store's subtree class: 0 for a zero bound, else `150 + k` for the smallest power of
/// two `2^k` at least `b` (`k` in `−149..=128`); decoded by [`pow2_bound`].
pub fn pow2_class(b: f32) -> u32 {
    if b.is_nan() || b <= 0.0 {
        return 0;
    }
    let bits = b.to_bits();
    let (exponent, mantissa) = (bits >> 23 & 0xff, bits & 0x7f_ffff);
    let k = if exponent == 0 {
        // subnormal: mantissa · 2^−149
        (u32::BITS - (mantissa - 1).leading_zeros()) as i32 - 149
    } else if mantissa == 0 {
        exponent as i32 - 127
    } else {
        exponent as i32 - 126
    };
    (k + 150).min(MAX_POW2_CLASS as i32) as u32
}

/// The bound of lossless subtree class `c` ([`pow2_class`]): `2^(c − 150)`, `f32::MAX` for the
/// top class (whose power is not an f32).
pub fn pow2_bound(c: u32) -> f32 {
    let k = c as i32 - 150;
    match c {
        0 => 0.0,
        _ if k >= 128 => f32::MAX,
        _ if k >= -126 => f32::from_bits(((k + 127) as u32) << 23),
        _ => f32::from_bits(1 << (k + 149)),
    }
}

/// The decoded subtree bound of class `k`: `(2^k − 1) · step`, rounded up to an f32.
fn class_bound(k: u32, step: f32) -> f32 {
    let exact = ((1u64 << k) - 1) as f64 * step as f64;
    let b = exact as f32;
    if (b as f64) < exact {
        b.next_up()
    } else {
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes::box6;
    use crate::testing::{detail_nodes, unsampled_base};
    use proptest::prelude::*;

    fn harmonic(levels: u8) -> (BaseMesh, Vec<DetailNode>) {
        detail_nodes(unsampled_base(levels, box6([0.0; 3], [1.0; 3])), |p| {
            ((p[0] * 3.0).sin() * (p[1] * 2.0).cosh() + p[2] * p[2]) as f32
        })
    }

    /// The nodes as a quantized store holds them: codes times the step of node `id`'s quantizer
    /// `q(id)`.
    fn quantized(nodes: &[DetailNode], q: impl Fn(TetId) -> Quantizer) -> Vec<DetailNode> {
        nodes
            .iter()
            .map(|n| DetailNode {
                coeffs: n
                    .coeffs
                    .iter()
                    .map(|&c| q(n.id).decode(q(n.id).encode(c)))
                    .collect(),
                ..n.clone()
            })
            .collect()
    }

    /// The nodes as a lossless block carries them: subtree bounds rounded up to powers of two,
    /// none on the finest node level.
    fn pow2_bounds(base: &BaseMesh, nodes: &[DetailNode]) -> Vec<DetailNode> {
        let finest = base.forest().checked_finest_nodes_start().unwrap();
        nodes
            .iter()
            .map(|n| DetailNode {
                subtree_max_abs: if n.id >= finest {
                    INHERITED_BOUND
                } else {
                    pow2_bound(pow2_class(n.subtree_max_abs))
                },
                ..n.clone()
            })
            .collect()
    }

    fn bits(nodes: &[DetailNode]) -> Vec<Vec<u32>> {
        nodes
            .iter()
            .map(|n| n.coeffs.iter().map(|c| c.to_bits()).collect())
            .collect()
    }

    #[test]
    fn lossless_blocks_round_trip_exactly() {
        let (base, nodes) = harmonic(3);
        let coder = BlockCoder::new(&base, &Encoding::F32);
        let block = coder.encode(&nodes).unwrap();
        let back = coder.decode(&block).unwrap();
        assert_eq!(back, pow2_bounds(&base, &nodes));
        assert_eq!(bits(&back), bits(&nodes));
        for (a, b) in nodes.iter().zip(&back) {
            if b.subtree_max_abs == INHERITED_BOUND {
                continue;
            }
            assert!(b.subtree_max_abs >= a.subtree_max_abs);
            assert!(b.subtree_max_abs <= 2.0 * a.subtree_max_abs);
        }
        // the smooth field's details keep their zero low bits out of the stream
        let n_coeffs: usize = nodes.iter().map(|n| n.coeffs.len()).sum();
        assert!(
            block.bytes.len() * 10 < n_coeffs * 4 * 7,
            "{} bytes for {n_coeffs} coefficients",
            block.bytes.len()
        );
    }

    #[test]
    fn pow2_classes_bound_from_above_within_a_factor_two() {
        for b in [
            0.0f32,
            f32::from_bits(1),
            f32::from_bits(3),
            f32::MIN_POSITIVE,
            1e-30,
            0.75,
            1.0,
            1.5,
            3e38,
            f32::MAX,
        ] {
            let c = pow2_class(b);
            let up = pow2_bound(c);
            assert!(up >= b && up.is_finite(), "{b} → {up}");
            assert!(b == f32::MAX || up as f64 <= 2.0 * b as f64, "{b} → {up}");
            assert_eq!(pow2_class(up), c, "{b}");
        }
    }

    #[test]
    fn quantized_blocks_keep_codes_and_bound_subtrees() {
        let (base, nodes) = harmonic(4);
        let enc = Encoding::uniform(16, 1e-3);
        let q = enc.quantizer().unwrap().0;
        let nodes = quantized(&nodes, |_| q);
        let coder = BlockCoder::new(&base, &enc);
        // any subset, in any order
        let mut some: Vec<DetailNode> = nodes.iter().step_by(3).cloned().collect();
        some.reverse();
        let block = coder.encode(&some).unwrap();
        let back = coder.decode(&block).unwrap();
        some.sort_by_key(|n| n.id);
        assert_eq!(back.len(), some.len());
        for (a, b) in some.iter().zip(&back) {
            assert_eq!(
                (a.id, a.owned, a.empty_children),
                (b.id, b.owned, b.empty_children)
            );
            assert_eq!(a.coeffs, b.coeffs, "node {}", a.id);
            // the finest level's bounds are not coded, every other level's are
            let finest = base.forest().checked_finest_nodes_start().unwrap();
            assert_eq!(b.subtree_max_abs == INHERITED_BOUND, a.id >= finest);
            if a.id >= finest {
                continue;
            }
            assert!(b.subtree_max_abs >= a.subtree_max_abs, "node {}", a.id);
            // the class also covers the node's own codes (a residual of the quadratic
            // prediction may exceed the linear details the bound is about)
            let own = a.coeffs.iter().fold(0f32, |m, c| m.max(c.abs()));
            assert!(
                b.subtree_max_abs <= 2.0 * a.subtree_max_abs.max(own) + q.step,
                "node {}",
                a.id
            );
        }
        // what decodes re-codes to itself (the classes of decoded bounds are stable)
        assert_eq!(coder.decode(&coder.encode(&back).unwrap()).unwrap(), back);
        // all nodes: far below the 6-byte record plus 2-byte codes per coefficient
        let all = coder.encode(&nodes).unwrap();
        let fixed: usize = nodes.iter().map(|n| 6 + 2 * n.coeffs.len()).sum();
        assert!(
            all.bytes.len() * 4 < fixed,
            "{} vs {fixed}",
            all.bytes.len()
        );
    }

    /// View order sends whole sibling groups scattered over a level: their ids cost a couple of
    /// bits a group (a jump in groups, then a run), not a gap per node.
    #[test]
    fn scattered_sibling_groups_cost_little_in_ids() {
        let (base, nodes) = harmonic(4);
        let forest = base.forest();
        let coder = BlockCoder::new(&base, &Encoding::uniform(12, 1.0));
        // zero details: what is left to code is ids and near-free flags
        let zero = |n: &DetailNode| DetailNode {
            coeffs: vec![0.0; n.coeffs.len()],
            subtree_max_abs: 0.0,
            ..n.clone()
        };
        let finest = forest.checked_finest_nodes_start().unwrap();
        let mut some = Vec::new();
        let mut group = (finest - forest.n_base) / 8;
        for k in 0..100u64 {
            let first = (forest.n_base + 8 * group) as usize;
            some.extend(nodes[first..first + 8].iter().map(zero));
            group += 1 + (k * 7919) % 3;
        }
        let block = coder.encode(&some).unwrap();
        let ids = |ns: &[DetailNode]| ns.iter().map(|n| n.id).collect::<Vec<_>>();
        assert_eq!(ids(&coder.decode(&block).unwrap()), ids(&some));
        // under 4 bits a group
        assert!(
            block.bytes.len() < 50,
            "{} bytes for the ids of 100 groups",
            block.bytes.len()
        );
    }

    /// With level steps each node level's codes are in its own step: nodes quantized level by
    /// level come back as they were.
    #[test]
    fn level_steps_code_each_level_in_its_step() {
        use crate::wavelet::LevelSteps;
        let (base, nodes) = harmonic(4);
        let forest = base.forest();
        let enc = Encoding::Quantized {
            bits: 16,
            step: 1e-3,
            levels: LevelSteps::AXES,
        };
        let (q, steps) = enc.quantizer().unwrap();
        let at = |id: u64| steps.at(q, (forest.levels - 1 - forest.level(id)) as u32);
        let nodes = quantized(&nodes, at);
        let coder = BlockCoder::new(&base, &enc);
        let back = coder.decode(&coder.encode(&nodes).unwrap()).unwrap();
        for (a, b) in nodes.iter().zip(&back) {
            assert_eq!(a.coeffs, b.coeffs, "node {}", a.id);
        }
        // the base level's step, 3 levels above the finest, is 1/1.953125 of the finest's: its
        // values are not all on the finest level's grid of steps
        assert_eq!(at(0).step, q.step / 1.953125);
        assert!(nodes[..6]
            .iter()
            .flat_map(|n| &n.coeffs)
            .any(|c| (c / q.step).fract().abs() > 0.25));
    }

    /// Only a level with parents goes without bounds: with one level the base tets, which have no
    /// parent to borrow from, code theirs.
    #[test]
    fn one_level_codes_every_bound() {
        let (base, nodes) = harmonic(1);
        assert_eq!(base.forest().checked_finest_nodes_start(), None);
        for enc in [Encoding::F32, Encoding::uniform(12, 1e-3)] {
            let coder = BlockCoder::new(&base, &enc);
            let back = coder.decode(&coder.encode(&nodes).unwrap()).unwrap();
            for (a, b) in nodes.iter().zip(&back) {
                assert!(b.subtree_max_abs.is_finite(), "node {}", b.id);
                assert!(b.subtree_max_abs >= a.subtree_max_abs, "node {}", b.id);
            }
        }
    }

    /// A class whose bound does not fit in f32 under the decoder's step (a block coded for
    /// another quantizer) is refused, not decoded as an infinite bound on a level that codes one.
    #[test]
    fn a_bound_beyond_f32_is_refused() {
        let (base, nodes) = harmonic(3);
        let node = DetailNode {
            coeffs: vec![0.0; nodes[0].coeffs.len()],
            subtree_max_abs: (1u64 << 39) as f32,
            ..nodes[0].clone()
        };
        let at = |step| BlockCoder::new(&base, &Encoding::uniform(12, step));
        let block = at(1.0).encode(std::slice::from_ref(&node)).unwrap();
        assert!(at(1.0).decode(&block).is_ok());
        assert!(matches!(
            at(1e30).decode(&block),
            Err(BlockError::BadNode { .. })
        ));
    }

    #[test]
    fn a_mask_that_differs_from_the_hierarchy_still_round_trips() {
        let (base, mut nodes) = harmonic(2);
        let coder = BlockCoder::new(&base, &Encoding::F32);
        nodes[3].owned = 0;
        nodes[3].coeffs.clear();
        let block = coder.encode(&nodes[..10]).unwrap();
        assert_eq!(
            coder.decode(&block).unwrap(),
            pow2_bounds(&base, &nodes[..10])
        );
    }

    #[test]
    fn encoder_refuses_duplicates_and_foreign_ids() {
        let (base, nodes) = harmonic(2);
        let coder = BlockCoder::new(&base, &Encoding::F32);
        let dup = vec![nodes[1].clone(), nodes[1].clone()];
        assert_eq!(coder.encode(&dup), Err(BlockError::Duplicate(nodes[1].id)));
        let mut far = nodes[0].clone();
        far.id = base.forest().nodes();
        assert!(matches!(
            coder.encode(&[far]),
            Err(BlockError::IdOutOfRange { .. })
        ));
    }

    proptest! {
        #[test]
        fn lossless_coefficients_keep_every_bit(raw in proptest::collection::vec(any::<u32>(), 1..60), bound in any::<u32>()) {
            let (base, _) = harmonic(2);
            let coder = BlockCoder::new(&base, &Encoding::F32);
            // any finite f32: subnormals, both zeros, extreme exponents
            let coeffs: Vec<f32> = raw.iter().map(|&b| f32::from_bits(b)).filter(|c| c.is_finite()).collect();
            let bound = f32::from_bits(bound & 0x7fff_ffff);
            let nodes: Vec<DetailNode> = coeffs
                .chunks(6)
                .enumerate()
                .map(|(i, c)| DetailNode {
                    id: i as u64 * 2,
                    owned: ((1u16 << c.len()) - 1) as u8,
                    empty_children: 0,
                    subtree_max_abs: if bound.is_finite() { bound } else { 1.0 },
                    coeffs: c.to_vec(),
                })
                .collect();
            let back = coder.decode(&coder.encode(&nodes).unwrap()).unwrap();
            prop_assert_eq!(bits(&back), bits(&nodes));
            prop_assert_eq!(back, pow2_bounds(&base, &nodes));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        #[test]
        fn decoding_any_block_is_total(count in 0u32..300, first in 0u64..400, bytes in proptest::collection::vec(any::<u8>(), 0..256), kind in 0u8..3) {
            let (base, _) = harmonic(2);
            let steep = crate::wavelet::LevelSteps { ratio: 16.0, cap: 16.0 };
            let enc = match kind {
                0 => Encoding::F32,
                1 => Encoding::uniform(12, 0.01),
                _ => Encoding::Quantized { bits: 12, step: 0.01, levels: steep },
            };
            let coder = BlockCoder::new(&base, &enc);
            if let Ok(nodes) = coder.decode(&NodeBlock { count, first, bytes }) {
                prop_assert_eq!(nodes.len(), count as usize);
                for w in nodes.windows(2) { prop_assert!(w[0].id < w[1].id); }
                for n in &nodes { prop_assert!(n.validate().is_ok()); }
            }
        }
    }
}
