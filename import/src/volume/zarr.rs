//! Zarr arrays (v2 `.zarray`, v3 `zarr.json`) and OME-Zarr images (NGFF 0.4 and 0.5), from a
//! local folder or from object storage (`s3://BUCKET/PREFIX`, `http(s)://HOST/PATH`), read with
//! the `zarrs` crate.
//!
//! What is read:
//! - an array: v2 (C or F order, compressors blosc, zstd, gzip, zlib; zarr-python's defaults) or
//!   v3 (codecs bytes, transpose, gzip, zstd, blosc, crc32c, `sharding_indexed`), either byte
//!   order, of one of the eight sample types (u8, i8, u16, i16, u32, i32, f32, f64). int64,
//!   uint64, float16, bool, complex and strings are refused: no scalar field of the renderer
//!   holds them exactly.
//! - an OME-Zarr group (`multiscales` in `.zattrs` for 0.4, `ome.multiscales` in `zarr.json`
//!   for 0.5; `bioformats2raw.layout`'s image `0`): its finest level (`datasets[0]`), the
//!   spacing and origin of its `scale` and `translation` (the dataset's, then the multiscale's,
//!   composed), the `axes`' names, kinds and units. An array opened directly that is a level of
//!   an OME-Zarr group (its parent) takes that level's geometry.
//! - a group without `multiscales` is refused with the list of its arrays (local folders only:
//!   object storage is not listed), so that the user names one.
//!
//! Axes: an array's dims are in C order (the last varies fastest), so file axis 0 is the last
//! space dim, axis 2 the first. The three space dims map to the world axes by name when they
//! are called x, y and z, otherwise in order (file axis 0 → x). A time dim is `--frame`, a
//! channel dim `--scalar` (index, `omero.channels` label, or `mag`); any other dim must have
//! size 1. The dims' kinds come from the OME axes, else from the array's dimension names (v3
//! `dimension_names`, v2 xarray's `_ARRAY_DIMENSIONS`: `x`, `y`, `z`, `t`/`time`,
//! `c`/`channel`; names none of which is one of these count as none), else from the count: a
//! 3D array is z, y, x, and a 4D/5D one is read only when its leading extra dims all have
//! size 1. Otherwise which dim is time and which channels is not stated, and a guess would
//! read channels as frames or the reverse, so such an array is refused asking for OME axes or
//! dimension names. Without OME metadata the spacing is 1 and the origin 0.
//!
//! Out of core: [`VolumeReader::read_box`] asks `zarrs` for the box only, which reads the chunks
//! the box overlaps and, in a shard, the shard's index and the inner chunks the box overlaps
//! (ranged reads), never a whole shard for a part of it. Memory is the box and the chunks being
//! decoded. A chunk missing from the store is the fill value (Zarr's rule).
//!
//! Object storage: the store crate's URLs, endpoint and credentials variables
//! (`AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`,
//! `AWS_ALLOW_HTTP`), retry policy and `object_store` version, under a `zarrs` storage of this
//! module's own (`remote`) rather than `zarrs_object_store` behind `zarrs`'s async-to-sync
//! adapter: that pair asks every object's size before reading it (a HEAD before each GET) and
//! turns every failure into a string, losing a refusal's kind. Here a metadata document or a
//! chunk is one GET, a shard's index one suffix range, neighbouring ranges one request; the
//! requests run on a runtime of their own, waited for by this synchronous reader. Metadata
//! refused (403) counts as absent while another key is looked for (buckets without the list
//! permission refuse what is not there); a refusal or failure that stops the read is one error
//! naming the object's URL, and no message carries a secret.

use super::samples::choose_component;
use super::{
    AxisMap, DType, FileHeader, Samples, ScalarChoice, VolumeError, VolumeFormat, VolumeOptions,
    VolumeReader,
};
use serde_json::{Map, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::{
    Array, ArrayCreateError, ArrayError, ArrayMetadata, ArrayMetadataV2, ArrayMetadataV3,
    ArraySubset,
};
use zarrs::storage::{ReadableStorageTraits, StoreKey};

type Storage = Arc<dyn ReadableStorageTraits>;

/// Whether `dir` is a Zarr array or group (v2 `.zarray`/`.zgroup`, v3 `zarr.json`).
pub(crate) fn is_zarr_dir(dir: &Path) -> bool {
    [".zarray", ".zgroup", "zarr.json"]
        .iter()
        .any(|f| dir.join(f).is_file())
}

/// Opens the Zarr array or OME-Zarr image at `path` (a folder, or a URL: see [`super::is_url`]).
pub(crate) fn open(
    path: &Path,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    open_source(&Source::open(path)?, options)
}

fn open_source(
    src: &Source,
    options: &VolumeOptions,
) -> Result<Box<dyn VolumeReader>, VolumeError> {
    let image = find_image(src)?;
    Ok(Box::new(ZarrReader::new(src, image, options)?))
}

/// Where a Zarr hierarchy is read from: its storage, what errors call it, and (remote) the
/// object storage whose failed requests errors report.
struct Source {
    name: PathBuf,
    storage: Storage,
    remote: Option<Arc<remote::ObjectStorage>>,
}

impl Source {
    fn open(path: &Path) -> Result<Source, VolumeError> {
        if super::is_url(path) {
            let objects = Arc::new(remote::ObjectStorage::connect(path)?);
            return Ok(Source {
                name: path.to_path_buf(),
                storage: objects.clone(),
                remote: Some(objects),
            });
        }
        if !path.is_dir() {
            return Err(VolumeError::usage(
                path,
                "a Zarr array or group is a folder (holding .zarray, .zgroup or zarr.json)",
            ));
        }
        let store = zarrs::filesystem::FilesystemStore::new(path).map_err(|e| {
            VolumeError::unsupported(path, "path", format!("cannot be a Zarr store: {e}"))
        })?;
        Ok(Source {
            name: path.to_path_buf(),
            storage: Arc::new(store),
            remote: None,
        })
    }

    /// The parent of a local folder or of a URL with a path (`None` at a bucket's or host's
    /// root).
    fn parent(&self) -> Option<(PathBuf, String)> {
        if self.remote.is_some() {
            let s = self.name.to_str()?.trim_end_matches('/');
            let (scheme, rest) = s.split_once("://")?;
            let (head, last) = rest.rsplit_once('/')?;
            if head.is_empty() || last.is_empty() {
                return None;
            }
            return Some((
                PathBuf::from(format!("{scheme}://{head}")),
                last.to_string(),
            ));
        }
        let name = self.name.file_name()?.to_str()?.to_string();
        let parent = self.name.parent().filter(|p| !p.as_os_str().is_empty())?;
        Some((parent.to_path_buf(), name))
    }

    /// The bytes of `key` (`None`: no such key), errors naming it.
    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, VolumeError> {
        let k = StoreKey::new(key).map_err(|e| VolumeError::bad(&self.name, key, e.to_string()))?;
        match self.storage.get(&k) {
            Ok(b) => Ok(b.map(|b| b.to_vec())),
            Err(e) => Err(self
                .failure()
                .unwrap_or_else(|| VolumeError::bad(&self.name, key, format!("cannot read: {e}")))),
        }
    }

    /// The error of the last failed object request, when this is object storage.
    fn failure(&self) -> Option<VolumeError> {
        self.remote.as_ref().and_then(|r| r.take_failure())
    }
}

/// A node's metadata: an array's, or a group's attributes.
enum Node {
    Array(Box<ArrayMetadata>),
    Group(Map<String, Value>),
}

/// `src.get(key)`, a refusal counted as no such key (buckets without the list permission
/// refuse what is not there) but kept in `refused` to report when nothing is found.
fn get_or_refused(
    src: &Source,
    key: &str,
    refused: &mut Option<VolumeError>,
) -> Result<Option<Vec<u8>>, VolumeError> {
    match src.get(key) {
        Err(e @ VolumeError::Io { .. })
            if matches!(&e, VolumeError::Io { source, .. }
                if source.kind() == std::io::ErrorKind::PermissionDenied) =>
        {
            refused.get_or_insert(e);
            Ok(None)
        }
        r => r,
    }
}

/// The node at `prefix` (`""` the root, else `a/b`), from `zarr.json`, `.zarray` or `.zgroup`,
/// and `.zattrs`; `None` when there is none.
fn probe(src: &Source, prefix: &str) -> Result<Option<Node>, VolumeError> {
    let key = |f: &str| {
        if prefix.is_empty() {
            f.to_string()
        } else {
            format!("{prefix}/{f}")
        }
    };
    let json = |k: &str, bytes: &[u8]| -> Result<Map<String, Value>, VolumeError> {
        match serde_json::from_slice::<Value>(bytes) {
            Ok(Value::Object(m)) => Ok(m),
            Ok(_) => Err(VolumeError::bad(&src.name, k, "not a JSON object")),
            Err(e) => Err(VolumeError::bad(&src.name, k, format!("not JSON: {e}"))),
        }
    };
    let mut refused = None;
    let k3 = key("zarr.json");
    if let Some(b) = get_or_refused(src, &k3, &mut refused)? {
        let m = json(&k3, &b)?;
        if m.get("zarr_format").and_then(Value::as_u64) != Some(3) {
            return Err(VolumeError::unsupported(
                &src.name,
                &k3,
                format!(
                    "zarr_format {}: zarr.json is Zarr v3's",
                    m.get("zarr_format").unwrap_or(&Value::Null)
                ),
            ));
        }
        return match m.get("node_type").and_then(Value::as_str) {
            Some("array") => {
                let meta: ArrayMetadataV3 = serde_json::from_slice(&b)
                    .map_err(|e| VolumeError::bad(&src.name, &k3, e.to_string()))?;
                Ok(Some(Node::Array(Box::new(ArrayMetadata::V3(meta)))))
            }
            Some("group") => Ok(Some(Node::Group(match m.get("attributes") {
                Some(Value::Object(a)) => a.clone(),
                _ => Map::new(),
            }))),
            t => Err(VolumeError::bad(
                &src.name,
                &k3,
                format!("node_type {t:?}: give \"array\" or \"group\""),
            )),
        };
    }
    let k2 = key(".zarray");
    let array = get_or_refused(src, &k2, &mut refused)?;
    let group = match array {
        Some(_) => None,
        None => get_or_refused(src, &key(".zgroup"), &mut refused)?,
    };
    if array.is_none() && group.is_none() {
        return refused.map_or(Ok(None), Err);
    }
    let ka = key(".zattrs");
    let attrs = match get_or_refused(src, &ka, &mut None)? {
        Some(b) => json(&ka, &b)?,
        None => Map::new(),
    };
    Ok(Some(match array {
        Some(b) => {
            let mut meta: ArrayMetadataV2 = serde_json::from_slice(&b)
                .map_err(|e| VolumeError::bad(&src.name, &k2, e.to_string()))?;
            meta.attributes = attrs;
            Node::Array(Box::new(ArrayMetadata::V2(meta)))
        }
        None => Node::Group(attrs),
    }))
}

/// What a dim of an array is.
#[derive(Debug, Clone, PartialEq)]
enum Kind {
    /// A space dim, with its world axis when its name says it (x, y, z).
    Space(Option<usize>),
    Time,
    Channel,
    /// Another kind (read only when the dim has size 1), with what the metadata calls it.
    Other(String),
}

/// The kind a dim's name alone says (a dim with no kind of its own).
fn kind_of_name(name: &str) -> Kind {
    match name.to_ascii_lowercase().as_str() {
        "x" => Kind::Space(Some(0)),
        "y" => Kind::Space(Some(1)),
        "z" => Kind::Space(Some(2)),
        "t" | "time" => Kind::Time,
        "c" | "ch" | "channel" | "channels" => Kind::Channel,
        other => Kind::Other(other.to_string()),
    }
}

/// The image an array holds: the array's node and what OME-Zarr metadata says of it.
struct Image {
    /// The array's node path (`/`, `/0`, ...) and metadata.
    array: String,
    meta: Box<ArrayMetadata>,
    ome: Option<Ome>,
}

/// What an OME-Zarr multiscale says of one of its levels.
#[derive(Debug, Default)]
struct Ome {
    version: String,
    /// Each dim's kind and unit (`None`: no `axes`, the array's own names apply).
    axes: Option<Vec<(String, Kind, Option<String>)>>,
    /// `coordinateTransformations` composed: world = scale · index + translation, per dim.
    scale: Vec<f64>,
    translation: Vec<f64>,
    /// The level's path, and how many levels the multiscale has.
    level: String,
    levels: usize,
    /// `omero.channels[].label`.
    channels: Vec<String>,
    notes: Vec<String>,
}

fn find_image(src: &Source) -> Result<Image, VolumeError> {
    match probe(src, "")? {
        None => Err(VolumeError::unsupported(
            &src.name,
            "format",
            "no zarr.json, .zarray or .zgroup here: not a Zarr array or group",
        )),
        Some(Node::Array(meta)) => Ok(Image {
            array: "/".into(),
            meta,
            ome: parent_level(src),
        }),
        Some(Node::Group(attrs)) => group_image(src, "", &attrs, 0),
    }
}

/// The image of a group at `prefix`: its multiscale's finest level, or bioformats2raw's image
/// `0`; a group without either is refused with its arrays listed.
fn group_image(
    src: &Source,
    prefix: &str,
    attrs: &Map<String, Value>,
    depth: usize,
) -> Result<Image, VolumeError> {
    let section = if prefix.is_empty() {
        "group".to_string()
    } else {
        format!("group {prefix}")
    };
    if let Some(ome) = parse_multiscales(&src.name, &section, attrs, None)? {
        let array = if prefix.is_empty() {
            format!("/{}", ome.level)
        } else {
            format!("/{prefix}/{}", ome.level)
        };
        let key = array.trim_start_matches('/').to_string();
        return match probe(src, &key)? {
            Some(Node::Array(meta)) => Ok(Image {
                array,
                meta,
                ome: Some(ome),
            }),
            _ => Err(VolumeError::bad(
                &src.name,
                "multiscales",
                format!(
                    "datasets[0].path {:?}: no array there (no zarr.json or .zarray)",
                    ome.level
                ),
            )),
        };
    }
    if attrs.contains_key("bioformats2raw.layout") && depth == 0 {
        // bioformats2raw: the images are groups 0, 1, ...; the first one is read
        return match probe(src, "0")? {
            Some(Node::Group(a)) => {
                let mut image = group_image(src, "0", &a, depth + 1)?;
                if let Some(o) = image.ome.as_mut() {
                    o.notes
                        .push("bioformats2raw layout: image 0 of the series".into());
                }
                Ok(image)
            }
            _ => Err(VolumeError::bad(
                &src.name,
                "bioformats2raw.layout",
                "no image group 0",
            )),
        };
    }
    let arrays = list_children(src, prefix);
    Err(VolumeError::unsupported(
        &src.name,
        &section,
        if arrays.is_empty() {
            "a group without OME-Zarr multiscales: open one of its arrays (its folder or URL)"
                .to_string()
        } else {
            format!(
                "a group without OME-Zarr multiscales: open one of its arrays: {}",
                arrays.join(", ")
            )
        },
    ))
}

/// The arrays and groups right under a local group (names sorted); nothing for object storage
/// (not listed).
fn list_children(src: &Source, prefix: &str) -> Vec<String> {
    if src.remote.is_some() {
        return Vec::new();
    }
    let dir = src.name.join(prefix);
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok())
        .filter(|e| is_zarr_dir(&e.path()))
        .map(|e| {
            let name = e.file_name().to_string_lossy().to_string();
            let p = e.path();
            if p.join(".zarray").is_file() || zarr_json_is_array(&p) {
                name
            } else {
                format!("{name} (a group)")
            }
        })
        .collect();
    names.sort_by(|a, b| super::natural_cmp(a, b));
    names
}

fn zarr_json_is_array(dir: &Path) -> bool {
    std::fs::read(dir.join("zarr.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
        .is_some_and(|v| v.get("node_type").and_then(Value::as_str) == Some("array"))
}

/// When the array opened is a level of an OME-Zarr image (its parent folder or URL holds the
/// multiscales naming it), that level's geometry. Any failure there leaves the array on its
/// own.
fn parent_level(src: &Source) -> Option<Ome> {
    let (parent, name) = src.parent()?;
    let psrc = Source::open(&parent).ok()?;
    let Ok(Some(Node::Group(attrs))) = probe(&psrc, "") else {
        return None;
    };
    let mut ome = parse_multiscales(&psrc.name, "group", &attrs, Some(&name))
        .ok()
        .flatten()?;
    ome.notes.push(format!(
        "level {name} of the OME-Zarr image {}",
        parent.display()
    ));
    Some(ome)
}

/// The OME-Zarr multiscale of a group's attributes (0.5: `ome.multiscales`, 0.4 and before:
/// `multiscales`), for the dataset of path `level` (default the first, the finest). `None`:
/// no multiscales (or, with `level`, none of that path).
fn parse_multiscales(
    name: &Path,
    section: &str,
    attrs: &Map<String, Value>,
    level: Option<&str>,
) -> Result<Option<Ome>, VolumeError> {
    let bad = |m: String| VolumeError::bad(name, &format!("{section}: multiscales"), m);
    let (root, version) = match attrs.get("ome") {
        Some(Value::Object(o)) if o.contains_key("multiscales") => (
            o,
            o.get("version")
                .and_then(Value::as_str)
                .unwrap_or("0.5")
                .to_string(),
        ),
        _ => (attrs, String::new()),
    };
    let Some(ms) = root.get("multiscales") else {
        return Ok(None);
    };
    let list = ms.as_array().ok_or_else(|| bad("not a list".into()))?;
    let first = list
        .first()
        .ok_or_else(|| bad("an empty list".into()))?
        .as_object()
        .ok_or_else(|| bad("multiscales[0] is not an object".into()))?;
    let version = if version.is_empty() {
        first
            .get("version")
            .and_then(Value::as_str)
            .unwrap_or("0.4")
            .to_string()
    } else {
        version
    };
    let datasets = first
        .get("datasets")
        .and_then(Value::as_array)
        .filter(|d| !d.is_empty())
        .ok_or_else(|| bad("no datasets".into()))?;
    let pick = match level {
        None => 0,
        Some(l) => match datasets
            .iter()
            .position(|d| d.get("path").and_then(Value::as_str) == Some(l))
        {
            Some(k) => k,
            None => return Ok(None),
        },
    };
    let dataset = datasets[pick]
        .as_object()
        .ok_or_else(|| bad(format!("datasets[{pick}] is not an object")))?;
    let path = dataset
        .get("path")
        .and_then(Value::as_str)
        .ok_or_else(|| bad(format!("datasets[{pick}] has no path")))?;
    if path.is_empty()
        || path.starts_with('/')
        || path
            .split('/')
            .any(|p| p.is_empty() || p == "." || p == "..")
    {
        return Err(bad(format!(
            "datasets[{pick}].path {path:?}: give a relative path inside the group"
        )));
    }
    let axes = match first.get("axes") {
        None => None,
        Some(Value::Array(a)) => Some(
            a.iter()
                .enumerate()
                .map(|(k, ax)| parse_axis(ax).ok_or_else(|| bad(format!("axes[{k}]: {ax}"))))
                .collect::<Result<Vec<_>, _>>()?,
        ),
        Some(v) => return Err(bad(format!("axes: {v}: not a list"))),
    };
    let ndim = axes.as_ref().map(Vec::len);
    let mut scale: Vec<f64> = Vec::new();
    let mut translation: Vec<f64> = Vec::new();
    // the dataset's transformations, then the multiscale's
    for (what, t) in [
        (
            format!("datasets[{pick}].coordinateTransformations"),
            dataset.get("coordinateTransformations"),
        ),
        (
            "coordinateTransformations".to_string(),
            first.get("coordinateTransformations"),
        ),
    ] {
        let Some(t) = t else { continue };
        let list = t
            .as_array()
            .ok_or_else(|| bad(format!("{what}: not a list")))?;
        for (k, tr) in list.iter().enumerate() {
            let kind = tr.get("type").and_then(Value::as_str).unwrap_or("");
            if kind == "identity" {
                continue;
            }
            if tr.get("path").is_some() {
                return Err(VolumeError::unsupported(
                    name,
                    &format!("{section}: multiscales"),
                    format!("{what}[{k}]: a transformation stored in a file (path)"),
                ));
            }
            let values: Vec<f64> = match tr.get(kind).and_then(Value::as_array) {
                Some(v) if matches!(kind, "scale" | "translation") => v
                    .iter()
                    .map(|x| x.as_f64().filter(|x| x.is_finite()))
                    .collect::<Option<Vec<f64>>>()
                    .ok_or_else(|| bad(format!("{what}[{k}]: {kind} values must be numbers")))?,
                _ => {
                    return Err(VolumeError::unsupported(
                        name,
                        &format!("{section}: multiscales"),
                        format!(
                            "{what}[{k}]: transformation {kind:?} (read are scale and translation)"
                        ),
                    ))
                }
            };
            let n = ndim.unwrap_or(values.len());
            if values.len() != n || (!scale.is_empty() && scale.len() != n) {
                return Err(bad(format!(
                    "{what}[{k}]: {} {kind} values for {n} axes",
                    values.len()
                )));
            }
            if scale.is_empty() {
                scale = vec![1.0; n];
                translation = vec![0.0; n];
            }
            for d in 0..n {
                if kind == "scale" {
                    scale[d] *= values[d];
                    translation[d] *= values[d];
                } else {
                    translation[d] += values[d];
                }
            }
        }
    }
    let channels = root
        .get("omero")
        .or_else(|| attrs.get("omero"))
        .and_then(|o| o.get("channels"))
        .and_then(Value::as_array)
        .map(|c| {
            c.iter()
                .enumerate()
                .map(|(k, ch)| {
                    ch.get("label")
                        .and_then(Value::as_str)
                        .map_or_else(|| k.to_string(), str::to_string)
                })
                .collect()
        })
        .unwrap_or_default();
    let mut notes = Vec::new();
    if list.len() > 1 {
        notes.push(format!(
            "{} multiscales in the group: the first is read",
            list.len()
        ));
    }
    Ok(Some(Ome {
        version,
        axes,
        scale,
        translation,
        level: path.to_string(),
        levels: datasets.len(),
        channels,
        notes,
    }))
}

/// An OME axis: `{"name", "type", "unit"}` (0.4, 0.5) or a bare name (0.3).
fn parse_axis(ax: &Value) -> Option<(String, Kind, Option<String>)> {
    if let Some(n) = ax.as_str() {
        return Some((n.to_string(), kind_of_name(n), None));
    }
    let name = ax.get("name")?.as_str()?.to_string();
    let by_name = kind_of_name(&name);
    let kind = match ax.get("type").and_then(Value::as_str) {
        Some("space") => match by_name {
            Kind::Space(w) => Kind::Space(w),
            _ => Kind::Space(None),
        },
        Some("time") => Kind::Time,
        Some("channel") => Kind::Channel,
        Some(other) => Kind::Other(format!("{name} ({other})")),
        None => by_name,
    };
    let unit = ax.get("unit").and_then(Value::as_str).map(str::to_string);
    Some((name, kind, unit))
}

/// A length unit as the other formats write it (`um`, `mm`), from OME's UDUNITS-2 names.
fn short_unit(unit: &str) -> String {
    match unit {
        "micrometer" | "micron" => "um",
        "millimeter" => "mm",
        "nanometer" => "nm",
        "centimeter" => "cm",
        "meter" => "m",
        "picometer" => "pm",
        "kilometer" => "km",
        u => u,
    }
    .to_string()
}

/// The eight sample types read, from the array's data type.
fn dtype_of(t: &zarrs::array::DataType) -> Option<DType> {
    use zarrs::array::data_type as dt;
    Some(if t.is::<dt::UInt8DataType>() {
        DType::U8
    } else if t.is::<dt::Int8DataType>() {
        DType::I8
    } else if t.is::<dt::UInt16DataType>() {
        DType::U16
    } else if t.is::<dt::Int16DataType>() {
        DType::I16
    } else if t.is::<dt::UInt32DataType>() {
        DType::U32
    } else if t.is::<dt::Int32DataType>() {
        DType::I32
    } else if t.is::<dt::Float32DataType>() {
        DType::F32
    } else if t.is::<dt::Float64DataType>() {
        DType::F64
    } else {
        return None;
    })
}

/// Runs `f`, a panic inside `zarrs` (a malformed chunk it did not foresee) becoming `Err`.
fn no_panic<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "a panic".into())
    })
}

pub(crate) struct ZarrReader {
    name: PathBuf,
    remote: Option<Arc<remote::ObjectStorage>>,
    array: Array<dyn ReadableStorageTraits>,
    header: FileHeader,
    /// The array's sample type (the header's is f32/f64 for a channels' magnitude).
    stored: DType,
    /// The array dim of each file axis (axis 0, the fastest, is the last space dim).
    space: [usize; 3],
    /// The index read along each dim that is not a space dim (the frame, the channel, 0).
    fixed: Vec<u64>,
    /// The channel dim and its size, when there is one of more than one channel.
    channels: Option<(usize, usize)>,
    /// The channel read (`None`: the magnitude of all of them).
    which: Option<usize>,
}

impl ZarrReader {
    fn new(src: &Source, image: Image, options: &VolumeOptions) -> Result<Self, VolumeError> {
        let name = &src.name;
        let meta_section = if image.array == "/" {
            "array".to_string()
        } else {
            format!("array {}", image.array.trim_start_matches('/'))
        };
        if let ArrayMetadata::V3(m) = image.meta.as_ref() {
            // what Array::open checks of the metadata it reads
            if let Some((field, _)) = m
                .additional_fields
                .iter()
                .find(|(_, f)| f.must_understand())
            {
                return Err(VolumeError::unsupported(
                    name,
                    &meta_section,
                    format!("{field:?}: an extension this reader does not know"),
                ));
            }
        }
        let (storage, node, meta) = (src.storage.clone(), &image.array, *image.meta);
        let array = match no_panic(|| Array::new_with_metadata(storage, node, meta)) {
            Ok(Ok(a)) => a,
            Ok(Err(e)) => return Err(create_error(name, &meta_section, e)),
            Err(p) => {
                return Err(VolumeError::bad(
                    name,
                    &meta_section,
                    format!("metadata zarrs cannot use: {p}"),
                ))
            }
        };
        let shape: Vec<u64> = array.shape().to_vec();
        let ndim = shape.len();
        let stored = dtype_of(array.data_type()).ok_or_else(|| {
            VolumeError::unsupported(
                name,
                &meta_section,
                format!(
                    "data type {}: read are uint8, int8, uint16, int16, uint32, int32, float32, \
                     float64 (not 64-bit integers, float16, bool, complex or strings)",
                    array.data_type()
                ),
            )
        })?;
        let usage = |m: String| VolumeError::usage(name, m);
        let unsup = |m: String| VolumeError::unsupported(name, &meta_section, m);
        let ome = image.ome;
        if let Some(axes) = ome.as_ref().and_then(|o| o.axes.as_ref()) {
            if axes.len() != ndim {
                return Err(VolumeError::bad(
                    name,
                    "multiscales",
                    format!("{} axes for an array of {ndim} dims {shape:?}", axes.len()),
                ));
            }
        }
        if let Some(o) = ome.as_ref() {
            if !o.scale.is_empty() && o.scale.len() != ndim {
                return Err(VolumeError::bad(
                    name,
                    "multiscales",
                    format!(
                        "coordinateTransformations of {} axes for an array of {ndim} dims",
                        o.scale.len()
                    ),
                ));
            }
        }
        // each dim's kind: the OME axes', else the array's dimension names', else by count
        let dim_names: Option<Vec<String>> = array
            .dimension_names()
            .as_ref()
            .filter(|n| n.len() == ndim && n.iter().all(|s| s.is_some()))
            .map(|n| n.iter().map(|s| s.clone().unwrap_or_default()).collect())
            .or_else(|| {
                array
                    .attributes()
                    .get("_ARRAY_DIMENSIONS")
                    .and_then(Value::as_array)
                    .filter(|n| n.len() == ndim)
                    .and_then(|n| {
                        n.iter()
                            .map(|s| s.as_str().map(str::to_string))
                            .collect::<Option<Vec<_>>>()
                    })
            })
            // names that say nothing (xarray's dim_0, ...) are no names
            .filter(|n| n.iter().any(|s| !matches!(kind_of_name(s), Kind::Other(_))));
        let mut notes: Vec<String> = Vec::new();
        let (names, kinds): (Vec<String>, Vec<Kind>) =
            match (ome.as_ref().and_then(|o| o.axes.as_ref()), &dim_names) {
                (Some(axes), _) => axes.iter().map(|(n, k, _)| (n.clone(), k.clone())).unzip(),
                (None, Some(n)) => n.iter().map(|s| (s.clone(), kind_of_name(s))).unzip(),
                (None, None) if ndim == 3 => (
                    ["z", "y", "x"].map(String::from).to_vec(),
                    vec![
                        Kind::Space(Some(2)),
                        Kind::Space(Some(1)),
                        Kind::Space(Some(0)),
                    ],
                ),
                (None, None) if ndim > 3 && shape[..ndim - 3].iter().all(|&n| n == 1) => {
                    notes.push(format!(
                        "dims {shape:?}: the leading {} of size 1 dropped, the last three read \
                         as z, y, x",
                        ndim - 3
                    ));
                    let mut k = vec![Kind::Other("size 1".into()); ndim - 3];
                    k.extend([
                        Kind::Space(Some(2)),
                        Kind::Space(Some(1)),
                        Kind::Space(Some(0)),
                    ]);
                    let mut n: Vec<String> = (0..ndim - 3).map(|d| format!("dim {d}")).collect();
                    n.extend(["z", "y", "x"].map(String::from));
                    (n, k)
                }
                (None, None) if ndim > 3 => {
                    return Err(unsup(format!(
                        "a {ndim}D array of shape {shape:?} without OME-Zarr axes or dimension \
                         names: which dim is time and which are channels is not stated; open \
                         its OME-Zarr image group, or name its dims (t, c, z, y, x)"
                    )))
                }
                (None, None) => {
                    return Err(unsup(format!(
                        "a {ndim}D array of shape {shape:?}: a volume has 3 space dims"
                    )))
                }
            };
        let space_dims: Vec<usize> = (0..ndim)
            .filter(|&d| matches!(kinds[d], Kind::Space(_)))
            .collect();
        if space_dims.len() != 3 {
            return Err(unsup(format!(
                "dims {names:?} of shape {shape:?}: {} space dims, a volume has 3",
                space_dims.len()
            )));
        }
        let space = [space_dims[2], space_dims[1], space_dims[0]];
        let mut fixed = vec![0u64; ndim];
        let mut channels = None;
        let mut frame_dim = None;
        for d in 0..ndim {
            match &kinds[d] {
                Kind::Space(_) => {}
                Kind::Time if frame_dim.is_none() => frame_dim = Some(d),
                Kind::Channel if channels.is_none() => channels = Some((d, shape[d] as usize)),
                k if shape[d] == 1 => {
                    if !matches!(k, Kind::Other(s) if s == "size 1") {
                        notes.push(format!("dim {} of size 1 ignored", names[d]));
                    }
                }
                Kind::Other(what) => {
                    return Err(unsup(format!(
                        "dim {d} {what} of size {} (dims {names:?}): read are 3 space dims, \
                         one time and one channel dim",
                        shape[d]
                    )))
                }
                k => {
                    return Err(unsup(format!(
                        "dims {names:?}: a second {} dim",
                        if *k == Kind::Time { "time" } else { "channel" }
                    )))
                }
            }
        }
        // the frame
        let frames = frame_dim.map_or(1, |d| shape[d]);
        let frame = match (options.frame, frames) {
            (Some(t), n) if (t as u64) < n => t as u64,
            (Some(t), n) => {
                return Err(usage(format!(
                    "--frame {t}: the volume has {n} frame(s) (0 to {})",
                    n - 1
                )))
            }
            (None, 1) => 0,
            (None, n) => {
                return Err(usage(format!(
                    "{n} frames (a time axis): choose one with --frame T (0 to {})",
                    n - 1
                )))
            }
        };
        if let Some(d) = frame_dim {
            fixed[d] = frame;
            if frames > 1 {
                notes.push(format!("frame {frame} of {frames}"));
            }
        }
        // the channel
        let n_channels = channels.map_or(1, |(_, n)| n);
        let labels: Vec<String> = ome
            .as_ref()
            .map(|o| o.channels.clone())
            .filter(|c| c.len() == n_channels)
            .unwrap_or_default();
        let which = match (options.scalar.as_ref(), n_channels) {
            // one channel: its magnitude is itself
            (Some(ScalarChoice::Magnitude), 1) => Some(0),
            (choice, n) => choose_component(choice, n, &labels).map_err(usage)?,
        };
        let channels = channels.filter(|&(_, n)| n > 1);
        if let Some((d, n)) = channels {
            fixed[d] = which.unwrap_or(0) as u64;
            notes.push(match which {
                Some(k) if labels.len() == n => format!("channel {k} ({}) of {n}", labels[k]),
                Some(k) => format!("channel {k} of {n}"),
                None => format!("the magnitude of the {n} channels"),
            });
        }
        let dtype = match (which, channels) {
            (None, Some(_)) if stored == DType::F64 => DType::F64,
            (None, Some(_)) => DType::F32,
            _ => stored,
        };
        // geometry
        let dims = space.map(|d| shape[d] as usize);
        if space.iter().any(|&d| shape[d] > isize::MAX as u64) {
            return Err(VolumeError::bad(
                name,
                &meta_section,
                format!("shape {shape:?}: more voxels than can be indexed"),
            ));
        }
        let (mut spacing, mut origin_dim) = ([1.0; 3], [0.0; 3]);
        let mut axes = [0, 1, 2].map(|axis| AxisMap { axis, flip: false });
        if let Some(o) = ome.as_ref().filter(|o| !o.scale.is_empty()) {
            for a in 0..3 {
                let s = o.scale[space[a]];
                if s == 0.0 {
                    return Err(VolumeError::bad(
                        name,
                        "multiscales",
                        format!("scale 0 along {}", names[space[a]]),
                    ));
                }
                spacing[a] = s.abs();
                axes[a].flip = s < 0.0;
                origin_dim[a] = o.translation[space[a]];
            }
        }
        let by_name: Vec<usize> = space
            .iter()
            .filter_map(|&d| match kinds[d] {
                Kind::Space(w) => w,
                _ => None,
            })
            .collect();
        let mut sorted = by_name.clone();
        sorted.sort_unstable();
        if sorted == [0, 1, 2] {
            for a in 0..3 {
                axes[a].axis = by_name[a];
            }
        } else {
            notes.push(format!(
                "space dims {:?}: not x, y and z, read as z, y, x in array order",
                space_dims.iter().map(|&d| &names[d]).collect::<Vec<_>>()
            ));
        }
        let mut origin = [0.0; 3];
        for a in 0..3 {
            origin[axes[a].axis] = origin_dim[a];
        }
        let mut header = FileHeader::new(VolumeFormat::Zarr, dims, dtype, spacing);
        header.origin = origin;
        header.axes = axes;
        let version = match array.metadata() {
            zarrs::array::ArrayMetadata::V2(_) => "v2",
            zarrs::array::ArrayMetadata::V3(_) => "v3",
        };
        match ome {
            Some(o) => {
                let units: Vec<Option<String>> = match &o.axes {
                    Some(a) => space.iter().map(|&d| a[d].2.clone()).collect(),
                    None => Vec::new(),
                };
                if let Some(Some(u)) = units.first() {
                    if units.iter().all(|x| x.as_ref() == Some(u)) {
                        header.length_unit = Some(short_unit(u));
                    } else {
                        notes.push(format!("space units differ ({units:?}): none stated"));
                    }
                }
                notes.insert(
                    0,
                    format!(
                        "OME-Zarr {} (Zarr {version}): level {:?}, the finest of {}",
                        o.version, o.level, o.levels
                    ),
                );
                if o.scale.is_empty() {
                    notes.push("no coordinateTransformations: spacing 1".into());
                }
                notes.extend(o.notes);
            }
            None => notes.insert(
                0,
                format!("Zarr {version} array without OME-Zarr metadata: spacing 1"),
            ),
        }
        header.notes = notes;
        Ok(ZarrReader {
            name: name.clone(),
            remote: src.remote.clone(),
            array,
            header,
            stored,
            space,
            fixed,
            channels,
            which,
        })
    }

    /// The voxels of the box with `channel` along the channel dim (when there is one).
    fn retrieve(
        &self,
        lo: [usize; 3],
        hi: [usize; 3],
        channel: u64,
    ) -> Result<Samples, VolumeError> {
        let mut ranges: Vec<std::ops::Range<u64>> = self.fixed.iter().map(|&i| i..i + 1).collect();
        if let Some((d, _)) = self.channels {
            ranges[d] = channel..channel + 1;
        }
        for a in 0..3 {
            ranges[self.space[a]] = lo[a] as u64..hi[a] as u64;
        }
        let subset = ArraySubset::new_with_ranges(&ranges);
        let array = &self.array;
        let got = no_panic(|| -> Result<Samples, ArrayError> {
            Ok(match self.stored {
                DType::U8 => Samples::U8(array.retrieve_array_subset(&subset)?),
                DType::I8 => Samples::I8(array.retrieve_array_subset(&subset)?),
                DType::U16 => Samples::U16(array.retrieve_array_subset(&subset)?),
                DType::I16 => Samples::I16(array.retrieve_array_subset(&subset)?),
                DType::U32 => Samples::U32(array.retrieve_array_subset(&subset)?),
                DType::I32 => Samples::I32(array.retrieve_array_subset(&subset)?),
                DType::F32 => Samples::F32(array.retrieve_array_subset(&subset)?),
                DType::F64 => Samples::F64(array.retrieve_array_subset(&subset)?),
            })
        });
        let section = format!("voxels {lo:?}..{hi:?}");
        match got {
            Ok(Ok(s)) => Ok(s),
            Ok(Err(e)) => Err(self
                .remote
                .as_ref()
                .and_then(|r| r.take_failure())
                .unwrap_or_else(|| VolumeError::bad(&self.name, &section, e.to_string()))),
            Err(p) => Err(VolumeError::bad(
                &self.name,
                &section,
                format!("a chunk zarrs cannot decode: {p}"),
            )),
        }
    }
}

/// The error of an array's metadata `zarrs` does not take: what it does not read is
/// "unsupported", the rest malformed.
fn create_error(name: &Path, section: &str, e: ArrayCreateError) -> VolumeError {
    match e {
        ArrayCreateError::DataTypeCreateError(e) => {
            VolumeError::unsupported(name, section, format!("data type: {e}"))
        }
        ArrayCreateError::CodecsCreateError(e) => {
            VolumeError::unsupported(name, section, format!("codecs: {e}"))
        }
        ArrayCreateError::StorageTransformersCreateError(e) => {
            VolumeError::unsupported(name, section, format!("storage transformers: {e}"))
        }
        ArrayCreateError::ChunkGridCreateError(e) => {
            VolumeError::unsupported(name, section, format!("chunk grid: {e}"))
        }
        e => VolumeError::bad(name, section, e.to_string()),
    }
}

impl VolumeReader for ZarrReader {
    fn header(&self) -> &FileHeader {
        &self.header
    }

    fn read_box(&mut self, lo: [usize; 3], hi: [usize; 3]) -> Result<Samples, VolumeError> {
        let dims = self.header.dims;
        super::check_box(&self.name, lo, hi, dims)?;
        match (self.which, self.channels) {
            (None, Some((_, n))) => {
                // the Euclidean norm of every channel, one channel's box at a time
                let voxels: usize = (0..3).map(|a| hi[a] - lo[a]).product();
                let mut sum = vec![0.0f64; voxels];
                for c in 0..n {
                    let s = self.retrieve(lo, hi, c as u64)?;
                    for (i, acc) in sum.iter_mut().enumerate() {
                        *acc += s.get(i).powi(2);
                    }
                }
                Ok(match self.header.dtype {
                    DType::F64 => Samples::F64(sum.into_iter().map(f64::sqrt).collect()),
                    _ => Samples::F32(sum.into_iter().map(|x| x.sqrt() as f32).collect()),
                })
            }
            (which, _) => self.retrieve(lo, hi, which.unwrap_or(0) as u64),
        }
    }
}

/// Zarr stores in object storage: S3-compatible buckets and HTTP(S) folders, read through
/// `object_store` as the store crate reads its files.
mod remote {
    use super::VolumeError;
    use object_store::path::Path as ObjectPath;
    use object_store::{GetOptions, GetRange, ObjectStore, ObjectStoreExt};
    use std::path::{Path, PathBuf};
    use std::sync::{Arc, Mutex};
    use std::time::Duration;
    use tetwave_store::location::{block_on, coalesce, request_timeout, RETRY, SHORT_READ_RETRIES};
    use tetwave_store::Location;
    use zarrs::storage::byte_range::{ByteRange, ByteRangeIterator};
    use zarrs::storage::{
        Bytes, MaybeBytes, MaybeBytesIterator, ReadableStorageTraits, StorageError, StoreKey,
    };

    /// A Zarr hierarchy's objects, as `zarrs` storage (read-only, never listed).
    pub(crate) struct ObjectStorage {
        store: Arc<dyn ObjectStore>,
        prefix: String,
        location: Location,
        /// The first request that failed since the last look: errors report it rather than
        /// what `zarrs` made of it.
        failure: Mutex<Option<(PathBuf, std::io::ErrorKind, String)>>,
    }

    impl ObjectStorage {
        /// Connects to the bucket or server of `url` (no request is made yet).
        pub(crate) fn connect(url: &Path) -> Result<ObjectStorage, VolumeError> {
            let location =
                Location::of_path(url).map_err(|e| VolumeError::usage(url, e.to_string()))?;
            let bad =
                |e: object_store::Error| VolumeError::usage(url, format!("cannot reach it: {e}"));
            let retry = object_store::RetryConfig {
                backoff: object_store::BackoffConfig {
                    init_backoff: RETRY.init_backoff,
                    max_backoff: RETRY.max_backoff,
                    base: 2.0,
                },
                max_retries: RETRY.max_retries,
                retry_timeout: RETRY.timeout,
            };
            let options = object_store::ClientOptions::new()
                .with_timeout(request_timeout())
                .with_connect_timeout(Duration::from_secs(5));
            let (store, prefix): (Arc<dyn ObjectStore>, String) = match &location {
                Location::S3 { bucket, prefix } => {
                    let allow_http = std::env::var("AWS_ALLOW_HTTP")
                        .is_ok_and(|v| matches!(v.to_ascii_lowercase().as_str(), "true" | "1"));
                    let s = object_store::aws::AmazonS3Builder::from_env()
                        .with_bucket_name(bucket)
                        .with_retry(retry)
                        .with_client_options(options.with_allow_http(allow_http))
                        .build()
                        .map_err(bad)?;
                    (Arc::new(s), prefix.clone())
                }
                Location::Http { root, prefix } => {
                    let s = object_store::http::HttpBuilder::new()
                        .with_url(root)
                        .with_retry(retry)
                        .with_client_options(options.with_allow_http(true))
                        .build()
                        .map_err(bad)?;
                    (Arc::new(s), prefix.clone())
                }
                Location::Dir(_) => {
                    return Err(VolumeError::usage(
                        url,
                        "not a URL (s3://BUCKET/PREFIX, http(s)://HOST/PATH)",
                    ))
                }
            };
            Ok(ObjectStorage {
                store,
                prefix,
                location,
                failure: Mutex::new(None),
            })
        }

        fn path(&self, key: &StoreKey) -> ObjectPath {
            if self.prefix.is_empty() {
                ObjectPath::from(key.as_str())
            } else {
                ObjectPath::from(format!("{}/{}", self.prefix, key.as_str()))
            }
        }

        /// The error of the first request that failed since the last call, naming its object.
        pub(crate) fn take_failure(&self) -> Option<VolumeError> {
            let (path, kind, message) = self.failure.lock().ok()?.take()?;
            Some(VolumeError::Io {
                path,
                source: std::io::Error::new(kind, message),
            })
        }

        /// Records a failed request on `key` (the first one since the last look) and gives
        /// `zarrs` its error.
        fn fail(&self, key: &StoreKey, kind: std::io::ErrorKind, message: String) -> StorageError {
            let path = self.location.name(key.as_str());
            let text = format!("{}: {message}", path.display());
            if let Ok(mut f) = self.failure.lock() {
                f.get_or_insert((path, kind, message));
            }
            StorageError::Other(text)
        }

        fn request_error(&self, key: &StoreKey, e: object_store::Error) -> StorageError {
            use std::io::ErrorKind;
            match e {
                object_store::Error::PermissionDenied { .. }
                | object_store::Error::Unauthenticated { .. } => self.fail(
                    key,
                    ErrorKind::PermissionDenied,
                    format!(
                        "access denied: check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY and the \
                         bucket's permissions ({e})"
                    ),
                ),
                e => {
                    let text = e.to_string();
                    // an HTTP server's refusal comes as a generic error with its status
                    if ["401 Unauthorized", "403 Forbidden"]
                        .iter()
                        .any(|s| text.contains(s))
                    {
                        let by = match self.location {
                            Location::S3 { .. } => {
                                "check AWS_ACCESS_KEY_ID, \
                                                   AWS_SECRET_ACCESS_KEY and the bucket's \
                                                   permissions"
                            }
                            _ => "the server refused it",
                        };
                        self.fail(
                            key,
                            ErrorKind::PermissionDenied,
                            format!("access denied: {by} ({text})"),
                        )
                    } else {
                        self.fail(key, ErrorKind::Other, text)
                    }
                }
            }
        }

        /// The bytes of `ranges` of `key` (`None`: no such object): ranges closer than
        /// [`COALESCE_GAP`](tetwave_store::location::COALESCE_GAP) fetched as one request, the requests concurrently, and one that
        /// comes short asked for again, up to [`SHORT_READ_RETRIES`] times.
        fn get_ranges(
            &self,
            key: &StoreKey,
            ranges: &[ByteRange],
        ) -> Result<Option<Vec<Bytes>>, StorageError> {
            let mut out: Vec<Option<Bytes>> = vec![None; ranges.len()];
            let mut asks: Vec<Ask> = Vec::new();
            let mut bounded: Vec<(usize, u64, u64)> = Vec::new();
            for (i, r) in ranges.iter().enumerate() {
                let whole = |range| Ask {
                    range,
                    len: None,
                    parts: vec![(i, 0, None)],
                };
                match *r {
                    ByteRange::FromStart(0, None) => asks.push(whole(None)),
                    ByteRange::FromStart(o, None) => asks.push(whole(Some(GetRange::Offset(o)))),
                    ByteRange::FromStart(_, Some(0)) | ByteRange::Suffix(0) => {
                        out[i] = Some(Bytes::new())
                    }
                    ByteRange::Suffix(n) => asks.push(Ask {
                        range: Some(GetRange::Suffix(n)),
                        len: Some(n),
                        parts: vec![(i, 0, Some(n))],
                    }),
                    ByteRange::FromStart(o, Some(n)) => {
                        let end = o.checked_add(n).ok_or_else(|| {
                            self.fail(
                                key,
                                std::io::ErrorKind::InvalidInput,
                                format!("byte range {o}+{n}"),
                            )
                        })?;
                        bounded.push((i, o, end));
                    }
                }
            }
            let (merged, which) = coalesce(&bounded.iter().map(|b| b.1..b.2).collect::<Vec<_>>());
            let mut members: Vec<Vec<(usize, u64, u64)>> = vec![Vec::new(); merged.len()];
            for (b, k) in bounded.into_iter().zip(which) {
                members[k].push(b);
            }
            for (m, members) in merged.into_iter().zip(members) {
                asks.push(Ask {
                    range: Some(GetRange::Bounded(m.clone())),
                    len: Some(m.end - m.start),
                    parts: members
                        .into_iter()
                        .map(|(i, a, b)| (i, a - m.start, Some(b - a)))
                        .collect(),
                });
            }
            let mut done = vec![false; asks.len()];
            for attempt in 0..=SHORT_READ_RETRIES {
                let todo: Vec<(usize, Option<GetRange>)> = (0..asks.len())
                    .filter(|&k| !done[k])
                    .map(|k| (k, asks[k].range.clone()))
                    .collect();
                if todo.is_empty() {
                    break;
                }
                let (store, path) = (self.store.clone(), self.path(key));
                let got = block_on(async move {
                    let mut set = tokio::task::JoinSet::new();
                    for (k, range) in todo {
                        let (store, path) = (store.clone(), path.clone());
                        set.spawn(async move {
                            let options = GetOptions {
                                range,
                                ..Default::default()
                            };
                            let r = store.get_opts(&path, options).await?;
                            let expect = r.range.end - r.range.start;
                            Ok::<_, object_store::Error>((k, expect, r.bytes().await?))
                        });
                    }
                    let mut got = Vec::new();
                    while let Some(j) = set.join_next().await {
                        got.push(j.map_err(|e| object_store::Error::Generic {
                            store: "tetwave",
                            source: Box::new(e),
                        })?);
                    }
                    Ok(got)
                });
                let got = match got {
                    Ok(g) => g,
                    Err(e) => return Err(self.request_error(key, e)),
                };
                for r in got {
                    let (k, expect, bytes) = match r {
                        Ok(x) => x,
                        Err(object_store::Error::NotFound { .. }) => return Ok(None),
                        Err(e) => return Err(self.request_error(key, e)),
                    };
                    let want = asks[k].len.unwrap_or(expect);
                    if bytes.len() as u64 == want && expect == want {
                        done[k] = true;
                        for &(i, at, len) in &asks[k].parts {
                            let (a, n) = (at as usize, len.unwrap_or(want) as usize);
                            out[i] = Some(bytes.slice(a..a + n));
                        }
                    } else if attempt == SHORT_READ_RETRIES {
                        return Err(self.fail(
                            key,
                            std::io::ErrorKind::UnexpectedEof,
                            format!(
                                "{:?}: {} bytes came of {want}, {} times",
                                asks[k].range,
                                bytes.len(),
                                attempt + 1
                            ),
                        ));
                    }
                }
            }
            Ok(Some(
                out.into_iter().map(Option::unwrap_or_default).collect(),
            ))
        }
    }

    /// Neighbouring bounded ranges fetched as one: its start and end, and each range's index,
    /// start and end.
    /// One request of [`ObjectStorage::get_ranges`]: the range asked (`None`: the whole
    /// object), the length it must come with (`None`: what the response says), and the ranges
    /// it serves (their index, offset in the response and length, `None`: all of it).
    struct Ask {
        range: Option<GetRange>,
        len: Option<u64>,
        parts: Vec<(usize, u64, Option<u64>)>,
    }

    impl ReadableStorageTraits for ObjectStorage {
        fn get(&self, key: &StoreKey) -> Result<MaybeBytes, StorageError> {
            Ok(self
                .get_ranges(key, &[ByteRange::FromStart(0, None)])?
                .and_then(|mut v| v.pop()))
        }

        fn get_partial_many<'a>(
            &'a self,
            key: &StoreKey,
            byte_ranges: ByteRangeIterator<'a>,
        ) -> Result<MaybeBytesIterator<'a>, StorageError> {
            let ranges: Vec<ByteRange> = byte_ranges.collect();
            Ok(self
                .get_ranges(key, &ranges)?
                .map(|v| Box::new(v.into_iter().map(Ok)) as Box<dyn Iterator<Item = _>>))
        }

        fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
            let (store, path) = (self.store.clone(), self.path(key));
            match block_on(async move { store.head(&path).await }) {
                Ok(meta) => Ok(Some(meta.size)),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(self.request_error(key, e)),
            }
        }

        fn supports_get_partial(&self) -> bool {
            true
        }
    }
}

#[cfg(test)]
#[path = "zarr_tests.rs"]
mod tests;
