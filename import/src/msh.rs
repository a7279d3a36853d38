//! gmsh `.msh` reader: formats 1.0 (ascii), 2.2 and 4.1, ascii and binary (either byte order).
//!
//! Written here rather than with `mshio` (see the parent module): `mshio` 0.4 has no 2.2, no
//! `$NodeData`, no parametric nodes, and loses the node numbering of contiguous-but-permuted tags.
//!
//! - Elements go through `gmsh_cell`: tets (4; 11, 29-31 by their corners), hexahedra,
//!   prisms and pyramids (split, see `split_cell`); the other elements are counted. In
//!   binary files the reader must know an element type's node count to read past it: types 1-31,
//!   92 and 93 are known, another type is an error.
//! - Node tags may be any positive numbers in any order: points are numbered in file order and
//!   element and `$NodeData` tags are mapped through the tags; a tag that no node has is an error.
//! - `$NodeData` blocks that give a value to every node become point arrays (1 component: point
//!   scalars; more: point vectors) named by their first string tag (a later block with the same
//!   name, e.g. another time step, gets `#2`, `#3`... appended); partial blocks are skipped.
//!   `$ElementData` blocks become cell arrays if every volume element has a value.
//! - Element tags become cell arrays as meshio names them: `gmsh:physical` (the physical group)
//!   and `gmsh:geometrical` (the elementary entity). In 1.0 and 2.2 they are the element's first
//!   two tags; in 4.1 the geometrical tag is the block's entity and the physical one the entity's
//!   first physical tag in `$Entities`. An array is kept when every volume element has a value
//!   (other elements without one get NaN).
//! - Other sections (`$PhysicalNames`, ...) are skipped by looking for their `$End` line. gmsh
//!   4.0 and 3.x are refused.

use std::collections::HashMap;

use super::cells::{check_nodes, gmsh_cell, Cell};
use super::lex::{capacity, show, Bad, Endian, Lex, Res};
use super::mesh::{FieldArray, ImportedMesh, ScalarArray};

/// Nodes of a gmsh element type (needed to read past elements in binary files).
fn nodes_per_element(t: i64) -> Option<usize> {
    Some(match t {
        1 => 2,
        2 => 3,
        3 | 4 => 4,
        5 => 8,
        6 => 6,
        7 => 5,
        8 => 3,
        9 => 6,
        10 => 9,
        11 => 10,
        12 => 27,
        13 => 18,
        14 => 14,
        15 => 1,
        16 => 8,
        17 => 20,
        18 => 15,
        19 => 13,
        20 => 9,
        21 => 10,
        22 => 12,
        23 | 24 => 15,
        25 => 21,
        26 => 4,
        27 => 5,
        28 => 6,
        29 => 20,
        30 => 35,
        31 => 56,
        92 => 64,
        93 => 125,
        _ => return None,
    })
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Version {
    V2,
    V41,
}

struct Msh<'a> {
    lx: Lex<'a>,
    binary: bool,
    endian: Endian,
    size_t: usize,
    section: String,
}

/// `$NodeData` or `$ElementData`: name, components, (tag, first value index) entries, values.
struct TagData {
    name: String,
    components: usize,
    entries: Vec<u64>,
    values: Vec<f64>,
}

#[derive(Default)]
struct Raw {
    coords: Vec<[f64; 3]>,
    tags: Vec<u64>,
    /// Every element in file order: its tag, its kind and its node tags (volume cells only) as a
    /// range of `nodes`.
    cells: Vec<(u64, Cell, usize, usize)>,
    nodes: Vec<u64>,
    node_data: Vec<TagData>,
    element_data: Vec<TagData>,
    /// Per element, in file order: its physical and geometrical tags.
    cell_tags: Vec<Tags>,
    /// 4.1 `$Entities`: (dimension, entity tag) → its first physical tag.
    entities: HashMap<(i64, i64), i64>,
}

/// An element's tags: 1.0 and 2.2 give them on the element; 4.1 gives the entity (dimension and
/// tag) whose physical tag `$Entities` holds.
#[derive(Debug, Clone, Copy, Default)]
struct Tags {
    physical: Option<i64>,
    geometrical: Option<i64>,
    entity_dim: Option<i64>,
}

impl Tags {
    fn of(tags: &[i64]) -> Tags {
        Tags {
            physical: tags.first().copied(),
            geometrical: tags.get(1).copied(),
            entity_dim: None,
        }
    }
}

fn parse_num<T: std::str::FromStr>(tok: &[u8]) -> Option<T> {
    std::str::from_utf8(tok).ok()?.parse().ok()
}

impl<'a> Msh<'a> {
    fn bad(&self, reason: impl Into<String>) -> Bad {
        Bad::new(self.section.clone(), reason)
    }

    fn truncated(&self, what: &str) -> Bad {
        self.bad(format!("file is truncated: it ends while reading {what}"))
    }

    fn ascii<T: std::str::FromStr>(&mut self, what: &str) -> Res<T> {
        let tok = self.lx.token().ok_or_else(|| self.truncated(what))?;
        parse_num(tok).ok_or_else(|| self.bad(format!("expected {what}, found \"{}\"", show(tok))))
    }

    fn bytes<const N: usize>(&mut self, what: &str) -> Res<[u8; N]> {
        let run = self.lx.take(N).ok_or_else(|| self.truncated(what))?;
        let mut a = [0u8; N];
        a.copy_from_slice(run);
        Ok(a)
    }

    fn int(&mut self, what: &str) -> Res<i64> {
        if !self.binary {
            return self.ascii(what);
        }
        let b = self.bytes::<4>(what)?;
        Ok(i64::from(match self.endian {
            Endian::Little => i32::from_le_bytes(b),
            Endian::Big => i32::from_be_bytes(b),
        }))
    }

    fn real(&mut self, what: &str) -> Res<f64> {
        if !self.binary {
            return self.ascii(what);
        }
        let b = self.bytes::<8>(what)?;
        Ok(match self.endian {
            Endian::Little => f64::from_le_bytes(b),
            Endian::Big => f64::from_be_bytes(b),
        })
    }

    /// A `size_t` (4.1 binary) or an ascii count.
    fn size_t(&mut self, what: &str) -> Res<u64> {
        if !self.binary {
            return self.ascii(what);
        }
        Ok(match (self.size_t, self.endian) {
            (4, Endian::Little) => u64::from(u32::from_le_bytes(self.bytes::<4>(what)?)),
            (4, Endian::Big) => u64::from(u32::from_be_bytes(self.bytes::<4>(what)?)),
            (_, Endian::Little) => u64::from_le_bytes(self.bytes::<8>(what)?),
            (_, Endian::Big) => u64::from_be_bytes(self.bytes::<8>(what)?),
        })
    }

    fn count(&mut self, what: &str) -> Res<usize> {
        let v = self.size_t(what)?;
        usize::try_from(v).map_err(|_| self.bad(format!("{what} {v} is too large")))
    }

    /// A node or element tag: positive.
    fn tag(&mut self, wide: bool, what: &str) -> Res<u64> {
        let v = if wide {
            self.size_t(what)?
        } else {
            self.int(what)?.max(0).unsigned_abs()
        };
        if v == 0 {
            return Err(self.bad(format!("{what} must be positive")));
        }
        Ok(v)
    }

    /// In binary files, checks that `n` records of `record` bytes fit in what is left.
    fn need(&self, n: usize, record: usize, what: &str) -> Res<()> {
        if !self.binary {
            return Ok(());
        }
        let bytes = n.saturating_mul(record);
        if bytes > self.lx.remaining() {
            return Err(self.bad(format!(
                "file is truncated: {n} {what} need {bytes} bytes but only {} remain",
                self.lx.remaining()
            )));
        }
        Ok(())
    }

    /// The next line with something on it (ascii element records).
    fn record_line(&mut self, what: &str) -> Res<Vec<i64>> {
        loop {
            let line = self.lx.line().ok_or_else(|| self.truncated(what))?;
            if self.lx.remaining() == 0 {
                // A whole section ends with its $End line: this one was cut.
                return Err(self.truncated(what));
            }
            let toks: Vec<&[u8]> = line
                .split(u8::is_ascii_whitespace)
                .filter(|t| !t.is_empty())
                .collect();
            if toks.is_empty() {
                continue;
            }
            return toks
                .iter()
                .map(|t| {
                    parse_num(t).ok_or_else(|| {
                        self.bad(format!(
                            "expected integers in {what}, found \"{}\"",
                            show(t)
                        ))
                    })
                })
                .collect();
        }
    }
}

pub(super) fn parse_msh(bytes: &[u8]) -> Res<ImportedMesh> {
    let mut m = Msh {
        lx: Lex::new(bytes),
        binary: false,
        endian: Endian::Little,
        size_t: 8,
        section: "$MeshFormat".into(),
    };
    match m.lx.token() {
        Some(b"$MeshFormat") => {}
        Some(b"$NOD") | Some(b"$PTS") => return parse_msh1(bytes),
        _ => return Err(m.bad("not a gmsh file: it does not start with $MeshFormat")),
    }
    let version_tok =
        m.lx.token()
            .ok_or_else(|| m.truncated("the format version"))?;
    let version = match version_tok {
        b"2" | b"2.0" | b"2.1" | b"2.2" => Version::V2,
        b"4.1" => Version::V41,
        v => {
            return Err(m.bad(format!(
                "gmsh format version {} is not supported (2.2 and 4.1 are; save with Mesh.MshFileVersion = 4.1)",
                show(v)
            )))
        }
    };
    let file_type: u32 = m.ascii("the file type (0 or 1)")?;
    m.binary = match file_type {
        0 => false,
        1 => true,
        t => return Err(m.bad(format!("file type {t} is neither 0 (ascii) nor 1 (binary)"))),
    };
    let data_size: usize = m.ascii("the data size")?;
    match (version, data_size) {
        (Version::V2, 8) => {}
        (Version::V41, 4 | 8) => m.size_t = data_size,
        (_, d) => return Err(m.bad(format!("data size {d} is not supported"))),
    }
    let _ = m.lx.line();
    if m.binary {
        let one = m.bytes::<4>("the binary endianness marker")?;
        m.endian = if i32::from_le_bytes(one) == 1 {
            Endian::Little
        } else if i32::from_be_bytes(one) == 1 {
            Endian::Big
        } else {
            return Err(m.bad("the binary endianness marker is not 1"));
        };
    }
    expect_end(&mut m, "MeshFormat", "$End")?;

    let mut raw = Raw::default();
    let (mut has_nodes, mut has_elements) = (false, false);
    while let Some(tok) = m.lx.token() {
        let Some(name) = tok.strip_prefix(b"$") else {
            return Err(Bad::new(
                "file",
                format!("expected a section such as $Nodes, found \"{}\"", show(tok)),
            ));
        };
        let name = String::from_utf8_lossy(name).into_owned();
        m.section = format!("${name}");
        let _ = m.lx.line();
        match (name.as_str(), version) {
            ("Nodes", Version::V2) => nodes_v2(&mut m, &mut raw)?,
            ("Nodes", Version::V41) => nodes_v41(&mut m, &mut raw)?,
            ("Elements", Version::V2) => elements_v2(&mut m, &mut raw)?,
            ("Elements", Version::V41) => elements_v41(&mut m, &mut raw)?,
            ("Entities", Version::V41) => entities_v41(&mut m, &mut raw)?,
            ("NodeData", _) => tag_data(&mut m, &mut raw, false)?,
            ("ElementData", _) => tag_data(&mut m, &mut raw, true)?,
            _ => {
                if !m.lx.skip_past(format!("$End{name}").as_bytes()) {
                    return Err(m.truncated(&format!("the section (no $End{name})")));
                }
                continue;
            }
        }
        expect_end(&mut m, &name, "$End")?;
        has_nodes |= name == "Nodes";
        has_elements |= name == "Elements";
    }
    if !has_nodes || !has_elements {
        let missing = if has_nodes { "$Elements" } else { "$Nodes" };
        return Err(Bad::new(
            missing,
            format!("the file has no {missing} section (truncated?)"),
        ));
    }
    resolve(raw)
}

fn expect_end(m: &mut Msh<'_>, name: &str, prefix: &str) -> Res<()> {
    let end = format!("{prefix}{name}");
    match m.lx.token() {
        Some(t) if t == end.as_bytes() => Ok(()),
        Some(t) => Err(m.bad(format!(
            "expected {end}, found \"{}\" (the counts disagree with the data)",
            show(t)
        ))),
        None => Err(m.truncated(&end)),
    }
}

fn nodes_v2(m: &mut Msh<'_>, raw: &mut Raw) -> Res<()> {
    let n: usize = m.ascii("the number of nodes")?;
    let _ = m.lx.line();
    m.need(n, 28, "nodes")?;
    let cap = capacity(n, 8, m.lx.remaining());
    raw.coords.reserve(cap);
    raw.tags.reserve(cap);
    for _ in 0..n {
        let tag = m.tag(false, "a node tag")?;
        let x = m.real("a node coordinate")?;
        let y = m.real("a node coordinate")?;
        let z = m.real("a node coordinate")?;
        raw.tags.push(tag);
        raw.coords.push([x, y, z]);
    }
    Ok(())
}

fn push_element(
    m: &Msh<'_>,
    raw: &mut Raw,
    tag: u64,
    ty: i64,
    nodes: &[i64],
    tags: Tags,
) -> Res<()> {
    let kind = gmsh_cell(ty);
    let start = raw.nodes.len();
    if let Cell::Volume { .. } = kind {
        check_nodes(kind, nodes.len(), &format!("element {tag} (type {ty})"))
            .map_err(|e| m.bad(e))?;
        for &v in nodes {
            raw.nodes
                .push(u64::try_from(v).ok().filter(|&v| v > 0).ok_or_else(|| {
                    m.bad(format!(
                        "element {tag} refers to node {v}, which $Nodes does not define"
                    ))
                })?);
        }
    }
    raw.cells.push((tag, kind, start, raw.nodes.len() - start));
    raw.cell_tags.push(tags);
    Ok(())
}

fn elements_v2(m: &mut Msh<'_>, raw: &mut Raw) -> Res<()> {
    let n: usize = m.ascii("the number of elements")?;
    let _ = m.lx.line();
    if !m.binary {
        for _ in 0..n {
            let rec = m.record_line("an element")?;
            let (Some(&num), Some(&ty), Some(&ntags)) = (rec.first(), rec.get(1), rec.get(2))
            else {
                return Err(m.bad("an element line has fewer than 3 numbers"));
            };
            let nodes = usize::try_from(ntags)
                .ok()
                .and_then(|k| k.checked_add(3))
                .and_then(|start| rec.get(start..))
                .ok_or_else(|| {
                    m.bad(format!(
                        "element {num} has {ntags} tags but its line is shorter"
                    ))
                })?;
            let tags = rec.get(3..rec.len() - nodes.len()).unwrap_or_default();
            push_element(m, raw, num.unsigned_abs(), ty, nodes, Tags::of(tags))?;
        }
        return Ok(());
    }
    let mut done = 0usize;
    while done < n {
        let ty = m.int("an element type")?;
        let follow = m.int("an element count")?;
        let ntags = m.int("a tag count")?;
        let nn = nodes_per_element(ty).ok_or_else(|| {
            m.bad(format!(
                "unknown element type {ty}: cannot read past it in a binary file"
            ))
        })?;
        let (Ok(follow), Ok(ntags)) = (usize::try_from(follow), usize::try_from(ntags)) else {
            return Err(m.bad(format!(
                "negative count in an element block header ({follow}, {ntags})"
            )));
        };
        if follow > n - done {
            return Err(m.bad(format!(
                "an element block of {follow} overruns the {n} elements"
            )));
        }
        if ntags > 1 << 16 {
            return Err(m.bad(format!("{ntags} tags per element")));
        }
        let words = 1 + ntags + nn;
        m.need(follow, words * 4, "elements")?;
        let mut rec = Vec::with_capacity(words);
        for _ in 0..follow {
            rec.clear();
            for _ in 0..words {
                rec.push(m.int("an element")?);
            }
            let num = rec.first().copied().unwrap_or(0).unsigned_abs();
            let tags = Tags::of(rec.get(1..1 + ntags).unwrap_or_default());
            let nodes = rec.get(words - nn..).unwrap_or_default();
            push_element(m, raw, num, ty, nodes, tags)?;
        }
        done += follow;
    }
    Ok(())
}

fn nodes_v41(m: &mut Msh<'_>, raw: &mut Raw) -> Res<()> {
    let blocks = m.count("the number of node blocks")?;
    let n = m.count("the number of nodes")?;
    let _min = m.size_t("the minimum node tag")?;
    let _max = m.size_t("the maximum node tag")?;
    let mut total = 0usize;
    for _ in 0..blocks {
        let dim = m.int("an entity dimension")?;
        let _entity = m.int("an entity tag")?;
        let parametric = m.int("the parametric flag")?;
        let k = m.count("the number of nodes in a block")?;
        if k > n - total {
            return Err(m.bad(format!(
                "node blocks hold more than the {n} nodes announced"
            )));
        }
        let extra = match parametric {
            0 => 0,
            1 => usize::try_from(dim.clamp(0, 3)).unwrap_or(0),
            p => return Err(m.bad(format!("parametric flag {p} is neither 0 nor 1"))),
        };
        m.need(k, m.size_t + 8 * (3 + extra), "nodes")?;
        let cap = capacity(k, 4, m.lx.remaining());
        raw.tags.reserve(cap);
        raw.coords.reserve(cap);
        for _ in 0..k {
            raw.tags.push(m.tag(true, "a node tag")?);
        }
        for _ in 0..k {
            let x = m.real("a node coordinate")?;
            let y = m.real("a node coordinate")?;
            let z = m.real("a node coordinate")?;
            for _ in 0..extra {
                m.real("a parametric coordinate")?;
            }
            raw.coords.push([x, y, z]);
        }
        total += k;
    }
    if total != n {
        return Err(m.bad(format!(
            "the header announces {n} nodes but the blocks hold {total}"
        )));
    }
    Ok(())
}

fn elements_v41(m: &mut Msh<'_>, raw: &mut Raw) -> Res<()> {
    let blocks = m.count("the number of element blocks")?;
    let n = m.count("the number of elements")?;
    let _min = m.size_t("the minimum element tag")?;
    let _max = m.size_t("the maximum element tag")?;
    let mut total = 0usize;
    for _ in 0..blocks {
        let dim = m.int("an entity dimension")?;
        let entity = m.int("an entity tag")?;
        let ty = m.int("an element type")?;
        let tags = Tags {
            physical: None,
            geometrical: Some(entity),
            entity_dim: Some(dim),
        };
        let k = m.count("the number of elements in a block")?;
        if k > n - total {
            return Err(m.bad(format!(
                "element blocks hold more than the {n} elements announced"
            )));
        }
        if m.binary {
            let nn = nodes_per_element(ty).ok_or_else(|| {
                m.bad(format!(
                    "unknown element type {ty}: cannot read past it in a binary file"
                ))
            })?;
            m.need(k, (1 + nn) * m.size_t, "elements")?;
            let mut rec = Vec::with_capacity(1 + nn);
            for _ in 0..k {
                rec.clear();
                for _ in 0..=nn {
                    let v = m.size_t("an element")?;
                    rec.push(i64::try_from(v).unwrap_or(-1));
                }
                let tag = rec.first().copied().unwrap_or(0).unsigned_abs();
                push_element(m, raw, tag, ty, rec.get(1..).unwrap_or_default(), tags)?;
            }
        } else {
            let _ = m.lx.line();
            for _ in 0..k {
                let rec = m.record_line("an element")?;
                let tag = rec.first().copied().unwrap_or(0).unsigned_abs();
                push_element(m, raw, tag, ty, rec.get(1..).unwrap_or_default(), tags)?;
            }
        }
        total += k;
    }
    if total != n {
        return Err(m.bad(format!(
            "the header announces {n} elements but the blocks hold {total}"
        )));
    }
    Ok(())
}

/// 4.1 `$Entities`: points, curves, surfaces and volumes with their physical tags (the first is
/// kept); bounding boxes and boundaries are read past.
fn entities_v41(m: &mut Msh<'_>, raw: &mut Raw) -> Res<()> {
    let counts = [
        m.count("the number of points")?,
        m.count("the number of curves")?,
        m.count("the number of surfaces")?,
        m.count("the number of volumes")?,
    ];
    for (dim, &n) in counts.iter().enumerate() {
        // tag, coordinates (a point) or a bounding box, the physical tag count.
        let least = 4 + if dim == 0 { 24 } else { 48 } + m.size_t;
        m.need(n, least, "entities")?;
        for _ in 0..n {
            let tag = m.int("an entity tag")?;
            for _ in 0..if dim == 0 { 3 } else { 6 } {
                m.real("an entity coordinate")?;
            }
            let np = m.count("the number of physical tags")?;
            m.need(np, 4, "physical tags")?;
            for k in 0..np {
                let p = m.int("a physical tag")?;
                if k == 0 {
                    raw.entities.insert((dim as i64, tag), p);
                }
            }
            if dim > 0 {
                let nb = m.count("the number of bounding entities")?;
                m.need(nb, 4, "bounding entities")?;
                for _ in 0..nb {
                    m.int("a bounding entity tag")?;
                }
            }
        }
    }
    Ok(())
}

/// `$NodeData` and `$ElementData` (same layout in 2.2 and 4.1): string, real and integer tags in
/// ascii, then `tag value...` records (binary: a 4-byte int and doubles).
fn tag_data(m: &mut Msh<'_>, raw: &mut Raw, elements: bool) -> Res<()> {
    let saved = m.binary;
    m.binary = false;
    let nstr: usize = m.ascii("the number of string tags")?;
    let _ = m.lx.line();
    let mut strings = Vec::new();
    for _ in 0..nstr {
        let line = m.lx.line().ok_or_else(|| m.truncated("a string tag"))?;
        let s = String::from_utf8_lossy(line)
            .trim()
            .trim_matches('"')
            .to_string();
        strings.push(s);
    }
    let nreal: usize = m.ascii("the number of real tags")?;
    for _ in 0..nreal {
        m.ascii::<f64>("a real tag")?;
    }
    let nint: usize = m.ascii("the number of integer tags")?;
    let mut ints = Vec::new();
    for _ in 0..nint {
        ints.push(m.ascii::<i64>("an integer tag")?);
    }
    let _ = m.lx.line();
    m.binary = saved;

    let name = strings.first().cloned().unwrap_or_default();
    let (kind, what) = if elements {
        ("$ElementData", "element")
    } else {
        ("$NodeData", "node")
    };
    m.section = format!("{kind} \"{name}\"");
    let (Some(&ncomp), Some(&count)) = (ints.get(1), ints.get(2)) else {
        return Err(m.bad("fewer than 3 integer tags (time step, components, count)"));
    };
    let (Ok(ncomp), Ok(count)) = (usize::try_from(ncomp), usize::try_from(count)) else {
        return Err(m.bad(format!(
            "negative component count {ncomp} or value count {count}"
        )));
    };
    if ncomp == 0 || ncomp > 1 << 16 {
        return Err(m.bad(format!("{ncomp} components per {what}")));
    }
    m.need(count, 4 + 8 * ncomp, "values")?;
    let cap = capacity(count, 4, m.lx.remaining());
    let mut entries = Vec::with_capacity(cap);
    let mut values = Vec::with_capacity(cap.saturating_mul(ncomp).min(m.lx.remaining()));
    for _ in 0..count {
        entries.push(m.tag(false, &format!("an {what} tag"))?);
        for _ in 0..ncomp {
            values.push(m.real("a value")?);
        }
    }
    let data = TagData {
        name,
        components: ncomp,
        entries,
        values,
    };
    if elements {
        raw.element_data.push(data);
    } else {
        raw.node_data.push(data);
    }
    Ok(())
}

/// Node tag → point index.
enum TagIndex {
    Dense(Vec<u32>),
    Sparse(HashMap<u64, u32>),
}

impl TagIndex {
    fn new(tags: &[u64]) -> Res<TagIndex> {
        let section = "$Nodes";
        if u32::try_from(tags.len()).is_err() {
            return Err(Bad::new(
                section,
                format!("{} nodes do not fit 32-bit indices", tags.len()),
            ));
        }
        let max = tags.iter().copied().max().unwrap_or(0);
        let dense_limit = (tags.len() as u64).saturating_mul(4).saturating_add(1024);
        let dup = |t: u64| Bad::new(section, format!("node tag {t} appears twice"));
        if max <= dense_limit {
            let mut map = vec![u32::MAX; max as usize + 1];
            for (i, &t) in tags.iter().enumerate() {
                let slot = map
                    .get_mut(t as usize)
                    .ok_or_else(|| Bad::new(section, "bad node tag"))?;
                if *slot != u32::MAX {
                    return Err(dup(t));
                }
                *slot = i as u32;
            }
            Ok(TagIndex::Dense(map))
        } else {
            let mut map = HashMap::with_capacity(tags.len());
            for (i, &t) in tags.iter().enumerate() {
                if map.insert(t, i as u32).is_some() {
                    return Err(dup(t));
                }
            }
            Ok(TagIndex::Sparse(map))
        }
    }

    fn get(&self, tag: u64) -> Option<u32> {
        match self {
            TagIndex::Dense(v) => usize::try_from(tag)
                .ok()
                .and_then(|t| v.get(t))
                .copied()
                .filter(|&i| i != u32::MAX),
            TagIndex::Sparse(m) => m.get(&tag).copied(),
        }
    }
}

fn resolve(raw: Raw) -> Res<ImportedMesh> {
    let index = TagIndex::new(&raw.tags)?;
    let n = raw.coords.len();
    let mut mesh = ImportedMesh::default();
    let mut nodes = Vec::new();
    for &(etag, kind, start, len) in &raw.cells {
        nodes.clear();
        for &node in raw.nodes.get(start..start + len).unwrap_or_default() {
            nodes.push(index.get(node).ok_or_else(|| {
                Bad::new(
                    "$Elements",
                    format!("element {etag} refers to node {node}, which $Nodes does not define"),
                )
            })?);
        }
        mesh.push_cell(kind, &nodes);
    }
    mesh.mesh.points = raw.coords;
    for data in raw.node_data {
        let Some(a) = spread(data, n, "$NodeData", |t| index.get(t).map(|i| i as usize))? else {
            continue;
        };
        let unique = unique_name(&a.name, |u| {
            mesh.mesh.point_data.iter().any(|b| b.name == u)
                || mesh.point_vectors.iter().any(|b| b.name == u)
        });
        if a.components == 1 {
            mesh.mesh.point_data.push(ScalarArray {
                name: unique,
                values: a.values,
            });
        } else {
            mesh.point_vectors.push(FieldArray { name: unique, ..a });
        }
    }
    if !raw.element_data.is_empty() {
        let cells: HashMap<u64, usize> = raw
            .cells
            .iter()
            .enumerate()
            .map(|(i, c)| (c.0, i))
            .collect();
        let volume: Vec<bool> = raw
            .cells
            .iter()
            .map(|c| matches!(c.1, Cell::Volume { .. }))
            .collect();
        for data in raw.element_data {
            let section = format!("$ElementData \"{}\"", data.name);
            let Some(a) = spread(data, raw.cells.len(), "$ElementData", |t| {
                cells.get(&t).copied()
            })?
            else {
                continue;
            };
            // Values are needed on the volume cells only.
            let missing = volume
                .iter()
                .enumerate()
                .filter(|&(i, &v)| v && a.values.get(i * a.components).is_none_or(|x| x.is_nan()))
                .count();
            if missing > 0 {
                tracing::warn!("{section}: no value for {missing} volume elements: skipped");
                continue;
            }
            let unique = unique_name(&a.name, |u| mesh.cell_data.iter().any(|b| b.name == u));
            mesh.cell_data.push(FieldArray { name: unique, ..a });
        }
    }
    // The physical and geometrical tags, where every volume element has one.
    let physical = |t: &Tags| match t.entity_dim {
        Some(dim) => t
            .geometrical
            .and_then(|e| raw.entities.get(&(dim, e)).copied()),
        None => t.physical,
    };
    let physicals: Vec<Option<i64>> = raw.cell_tags.iter().map(physical).collect();
    let geometricals: Vec<Option<i64>> = raw.cell_tags.iter().map(|t| t.geometrical).collect();
    for (name, tags) in [
        ("gmsh:physical", physicals),
        ("gmsh:geometrical", geometricals),
    ] {
        let complete = raw
            .cells
            .iter()
            .zip(&tags)
            .all(|(c, t)| !matches!(c.1, Cell::Volume { .. }) || t.is_some());
        if !complete || raw.cells.is_empty() {
            continue;
        }
        let values = tags
            .iter()
            .map(|t| t.map_or(f64::NAN, |v| v as f64))
            .collect();
        let unique = unique_name(name, |u| mesh.cell_data.iter().any(|b| b.name == u));
        mesh.cell_data.push(FieldArray {
            name: unique,
            components: 1,
            values,
        });
    }
    Ok(mesh)
}

/// A name not taken yet: `name`, else `name#2`, `name#3`... (another time step of a field).
fn unique_name(name: &str, taken: impl Fn(&str) -> bool) -> String {
    let mut unique = name.to_string();
    let mut k = 1;
    while taken(&unique) {
        k += 1;
        unique = format!("{name}#{k}");
    }
    unique
}

/// Tagged values spread over `n` slots (NaN where none is given). `$NodeData` must give a value
/// to every node or is skipped (`None`); `$ElementData` is checked by the caller.
fn spread(
    data: TagData,
    n: usize,
    kind: &str,
    slot: impl Fn(u64) -> Option<usize>,
) -> Res<Option<FieldArray>> {
    let nc = data.components;
    let section = format!("{kind} \"{}\"", data.name);
    let mut values = vec![f64::NAN; n.saturating_mul(nc)];
    let mut set = vec![false; n];
    let mut filled = 0usize;
    for (k, &tag) in data.entries.iter().enumerate() {
        let i = slot(tag).ok_or_else(|| {
            let what = if kind == "$NodeData" {
                "node"
            } else {
                "element"
            };
            Bad::new(
                &section,
                format!("a value for {what} {tag}, which the file does not define"),
            )
        })?;
        let src = data.values.get(k * nc..(k + 1) * nc).unwrap_or_default();
        if let (Some(dst), Some(s)) = (values.get_mut(i * nc..(i + 1) * nc), set.get_mut(i)) {
            dst.copy_from_slice(src);
            if !*s {
                *s = true;
                filled += 1;
            }
        }
    }
    if kind == "$NodeData" && filled < n {
        tracing::warn!("{section} gives values to {filled} of {n} nodes: skipped");
        return Ok(None);
    }
    Ok(Some(FieldArray {
        name: data.name,
        components: nc,
        values,
    }))
}

// ------------------------------------------------------------------------------------------------
// gmsh 1.0: `$NOD` (`n`, then `tag x y z` lines) `$ENDNOD`, `$ELM` (`n`, then `tag type
// physical elementary nodes node...` lines) `$ENDELM`. ascii only.

fn parse_msh1(bytes: &[u8]) -> Res<ImportedMesh> {
    let mut m = Msh {
        lx: Lex::new(bytes),
        binary: false,
        endian: Endian::Little,
        size_t: 8,
        section: "$NOD".into(),
    };
    let mut raw = Raw::default();
    let (mut has_nodes, mut has_elements) = (false, false);
    while let Some(tok) = m.lx.token() {
        let name = String::from_utf8_lossy(tok).into_owned();
        m.section = name.clone();
        match name.as_str() {
            "$NOD" | "$PTS" => {
                let n: usize = m.ascii("the number of nodes")?;
                let cap = capacity(n, 8, m.lx.remaining());
                raw.coords.reserve(cap);
                raw.tags.reserve(cap);
                for _ in 0..n {
                    raw.tags.push(m.tag(false, "a node tag")?);
                    let x = m.real("a node coordinate")?;
                    let y = m.real("a node coordinate")?;
                    let z = m.real("a node coordinate")?;
                    raw.coords.push([x, y, z]);
                }
                expect_end(&mut m, if name == "$NOD" { "NOD" } else { "PTS" }, "$END")?;
                has_nodes = true;
            }
            "$ELM" => {
                let n: usize = m.ascii("the number of elements")?;
                let _ = m.lx.line();
                for _ in 0..n {
                    let rec = m.record_line("an element")?;
                    let (Some(&num), Some(&ty), Some(&nn)) = (rec.first(), rec.get(1), rec.get(4))
                    else {
                        return Err(m.bad("an element line has fewer than 5 numbers"));
                    };
                    let nodes = rec.get(5..).unwrap_or_default();
                    if usize::try_from(nn).ok() != Some(nodes.len()) {
                        return Err(m.bad(format!(
                            "element {num} announces {nn} nodes but its line has {}",
                            nodes.len()
                        )));
                    }
                    let tags = Tags::of(rec.get(2..4).unwrap_or_default());
                    push_element(&m, &mut raw, num.unsigned_abs(), ty, nodes, tags)?;
                }
                expect_end(&mut m, "ELM", "$END")?;
                has_elements = true;
            }
            _ => {
                let Some(rest) = name.strip_prefix('$') else {
                    return Err(Bad::new(
                        "file",
                        format!("expected a section such as $NOD, found \"{}\"", show(tok)),
                    ));
                };
                let end = format!("$END{rest}");
                if !m.lx.skip_past(end.as_bytes()) {
                    return Err(m.truncated(&format!("the section (no {end})")));
                }
            }
        }
    }
    if !has_nodes || !has_elements {
        let missing = if has_nodes { "$ELM" } else { "$NOD" };
        return Err(Bad::new(
            missing,
            format!("the file has no {missing} section (truncated?)"),
        ));
    }
    resolve(raw)
}
