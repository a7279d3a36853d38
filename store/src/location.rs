//! Where a store lives, and the one way its files are read: a directory on this machine, an
//! S3-compatible bucket (`s3://BUCKET/PREFIX`) or a read-only HTTP(S) folder
//! (`http(s)://HOST/PATH`), the last two through the `object_store` crate.
//!
//! Object storage is read by range requests and never listed. Its endpoint and credentials come
//! from the standard variables (`AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
//! `AWS_REGION`, `AWS_ALLOW_HTTP`); no error or log line carries a secret (errors name the
//! object and what went wrong, as `object_store` reports it). Transient failures (5xx, timeouts,
//! connection resets) are retried by `object_store` with exponential backoff ([`RETRY`]); a
//! body shorter than asked is read again here ([`SHORT_READ_RETRIES`]); anything else is one
//! error naming the object.

use crate::StoreError;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use std::future::Future;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

/// `object_store`'s retries of a request that failed transiently: up to 6 retries with backoff
/// from 100 ms doubling to at most 5 s, given up after 60 s in all.
pub const RETRY: RetryPolicy = RetryPolicy {
    max_retries: 6,
    init_backoff: Duration::from_millis(100),
    max_backoff: Duration::from_secs(5),
    timeout: Duration::from_secs(60),
};

/// How often a range that came back short (a truncated body) is asked for again before the read
/// fails.
pub const SHORT_READ_RETRIES: u32 = 3;

/// A request that takes longer than this fails (and is retried as above), unless
/// `TETWAVE_REQUEST_TIMEOUT` gives other seconds.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);

/// [`REQUEST_TIMEOUT`], or `TETWAVE_REQUEST_TIMEOUT` seconds when set to a positive number.
pub fn request_timeout() -> Duration {
    std::env::var("TETWAVE_REQUEST_TIMEOUT")
        .ok()
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|s| s.is_finite() && *s > 0.0)
        .map_or(REQUEST_TIMEOUT, Duration::from_secs_f64)
}

/// The retry settings given to `object_store` (its `RetryConfig`, stated here so that docs and
/// tests can name them).
#[derive(Debug, Clone, Copy)]
pub struct RetryPolicy {
    pub max_retries: usize,
    pub init_backoff: Duration,
    pub max_backoff: Duration,
    pub timeout: Duration,
}

/// Where a store is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    /// A directory on this machine.
    Dir(PathBuf),
    /// `s3://BUCKET[/PREFIX]`: any S3-compatible service (endpoint and credentials from the
    /// environment).
    S3 { bucket: String, prefix: String },
    /// `http(s)://HOST[:PORT]/PATH`: a folder on a static file server or CDN, read-only.
    Http { root: String, prefix: String },
}

impl Location {
    /// Parses what a user typed: `s3://…`, `http://…` or `https://…` as a URL, anything else as a
    /// path.
    pub fn parse(s: &str) -> Result<Location, StoreError> {
        let bad = |reason: &str| StoreError::Location {
            location: s.to_string(),
            reason: reason.to_string(),
        };
        if let Some(rest) = s.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            if bucket.is_empty() {
                return Err(bad("no bucket after s3://"));
            }
            return Ok(Location::S3 {
                bucket: bucket.to_string(),
                prefix: clean_prefix(prefix),
            });
        }
        for scheme in ["http://", "https://"] {
            if let Some(rest) = s.strip_prefix(scheme) {
                if rest.contains(['?', '#']) {
                    return Err(bad("a store's URL has no query or fragment"));
                }
                let (host, path) = rest.split_once('/').unwrap_or((rest, ""));
                if host.is_empty() {
                    return Err(bad("no host"));
                }
                return Ok(Location::Http {
                    root: format!("{scheme}{host}"),
                    prefix: clean_prefix(path),
                });
            }
        }
        if s.contains("://") {
            return Err(bad(
                "a store is a path, s3://BUCKET/PREFIX or http(s)://HOST/PATH",
            ));
        }
        Ok(Location::Dir(PathBuf::from(s)))
    }

    /// A location given as a path argument (what a command line's `PathBuf` holds: a directory, or
    /// a URL typed in its place).
    pub fn of_path(p: &Path) -> Result<Location, StoreError> {
        match p.to_str() {
            Some(s) => Location::parse(s),
            None => Ok(Location::Dir(p.to_path_buf())),
        }
    }

    /// Whether this is object storage (read by requests, not from a disk).
    pub fn is_remote(&self) -> bool {
        !matches!(self, Location::Dir(_))
    }

    /// The directory, for a local store.
    pub fn dir(&self) -> Option<&Path> {
        match self {
            Location::Dir(d) => Some(d),
            _ => None,
        }
    }

    /// What errors call `file` of this store: a path, or the object's URL.
    pub fn name(&self, file: &str) -> PathBuf {
        match self {
            Location::Dir(d) => d.join(file),
            _ => PathBuf::from(format!("{}/{file}", self.to_string().trim_end_matches('/'))),
        }
    }

    /// A location inside this one (`parts/part-0-of-4` of a store).
    pub fn join(&self, sub: &str) -> Location {
        let join = |p: &str| clean_prefix(&format!("{p}/{sub}"));
        match self {
            Location::Dir(d) => Location::Dir(d.join(sub)),
            Location::S3 { bucket, prefix } => Location::S3 {
                bucket: bucket.clone(),
                prefix: join(prefix),
            },
            Location::Http { root, prefix } => Location::Http {
                root: root.clone(),
                prefix: join(prefix),
            },
        }
    }
}

impl std::fmt::Display for Location {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Location::Dir(d) => write!(f, "{}", d.display()),
            Location::S3 { bucket, prefix } if prefix.is_empty() => write!(f, "s3://{bucket}"),
            Location::S3 { bucket, prefix } => write!(f, "s3://{bucket}/{prefix}"),
            Location::Http { root, prefix } if prefix.is_empty() => write!(f, "{root}"),
            Location::Http { root, prefix } => write!(f, "{root}/{prefix}"),
        }
    }
}

fn clean_prefix(p: &str) -> String {
    p.split('/')
        .filter(|s| !s.is_empty())
        .collect::<Vec<_>>()
        .join("/")
}

/// The runtime every object request runs on (`object_store` is async; the store's readers are
/// not): two worker threads, started on first use.
fn runtime() -> &'static tokio::runtime::Runtime {
    static RT: OnceLock<tokio::runtime::Runtime> = OnceLock::new();
    RT.get_or_init(|| {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("tetwave-object")
            .enable_all()
            .build()
            .expect("a tokio runtime for object storage")
    })
}

/// Runs `f` on the object runtime and waits for it: callable from any thread, a tokio worker's
/// included (the caller's thread blocks; a server calls from a blocking task). A request whose
/// task panicked is an error, not a panic here. Shared with the volume readers' Zarr storage.
pub fn block_on<T, F>(f: F) -> Result<T, object_store::Error>
where
    F: Future<Output = Result<T, object_store::Error>> + Send + 'static,
    T: Send + 'static,
{
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    runtime().spawn(async move {
        let _ = tx.send(f.await);
    });
    rx.recv().unwrap_or_else(|_| {
        Err(object_store::Error::Generic {
            store: "tetwave",
            source: "the request failed inside object_store (its task panicked)".into(),
        })
    })
}

/// Ranges of one object closer than this are fetched as one request.
pub const COALESCE_GAP: u64 = 64 << 10;

/// `ranges` of one object merged where they overlap or lie closer than [`COALESCE_GAP`]: the
/// merged ranges in ascending order, and for each range given the index of the merged one
/// holding it.
pub fn coalesce(ranges: &[Range<u64>]) -> (Vec<Range<u64>>, Vec<usize>) {
    let mut order: Vec<usize> = (0..ranges.len()).collect();
    order.sort_by_key(|&i| ranges[i].start);
    let mut merged: Vec<Range<u64>> = Vec::new();
    let mut which = vec![0; ranges.len()];
    for i in order {
        let r = &ranges[i];
        match merged.last_mut() {
            Some(m) if r.start <= m.end.saturating_add(COALESCE_GAP) => m.end = m.end.max(r.end),
            _ => merged.push(r.clone()),
        }
        which[i] = merged.len() - 1;
    }
    (merged, which)
}

/// A store's objects: `object_store` and the prefix its files are under.
#[derive(Clone, Debug)]
pub(crate) struct Objects {
    store: Arc<dyn ObjectStore>,
    prefix: String,
    location: Location,
}

impl Objects {
    /// Connects to `location`'s bucket or server (no request is made yet).
    pub(crate) fn connect(location: &Location) -> Result<Objects, StoreError> {
        let bad = |e: object_store::Error| StoreError::Location {
            location: location.to_string(),
            reason: e.to_string(),
        };
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
        let (store, prefix): (Arc<dyn ObjectStore>, &str) = match location {
            Location::Dir(_) => unreachable!("a directory is read from the disk"),
            Location::S3 { bucket, prefix } => {
                // the client options replace what from_env read: AWS_ALLOW_HTTP again
                let allow_http = std::env::var("AWS_ALLOW_HTTP")
                    .is_ok_and(|v| matches!(v.to_ascii_lowercase().as_str(), "true" | "1"));
                let s = object_store::aws::AmazonS3Builder::from_env()
                    .with_bucket_name(bucket)
                    .with_retry(retry)
                    .with_client_options(options.with_allow_http(allow_http))
                    .build()
                    .map_err(bad)?;
                (Arc::new(s), prefix)
            }
            Location::Http { root, prefix } => {
                let s = object_store::http::HttpBuilder::new()
                    .with_url(root)
                    .with_retry(retry)
                    .with_client_options(options.with_allow_http(true))
                    .build()
                    .map_err(bad)?;
                (Arc::new(s), prefix)
            }
        };
        Ok(Objects {
            store,
            prefix: prefix.to_string(),
            location: location.clone(),
        })
    }

    fn path(&self, file: &str) -> ObjectPath {
        if self.prefix.is_empty() {
            ObjectPath::from(file)
        } else {
            ObjectPath::from(format!("{}/{file}", self.prefix))
        }
    }

    /// The error for a failed request on `file`.
    fn error(&self, file: &str, e: object_store::Error) -> StoreError {
        let path = self.location.name(file);
        match e {
            object_store::Error::NotFound { .. } => StoreError::Io {
                path,
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such object"),
            },
            object_store::Error::PermissionDenied { .. }
            | object_store::Error::Unauthenticated { .. } => StoreError::Object {
                path,
                reason: format!(
                    "access denied: check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY and the \
                     bucket's permissions ({e})"
                ),
            },
            e => StoreError::Object {
                path,
                reason: e.to_string(),
            },
        }
    }

    /// `file`'s size, or `None` when there is no such object.
    pub(crate) fn size(&self, file: &str) -> Result<Option<u64>, StoreError> {
        let (store, path) = (self.store.clone(), self.path(file));
        match block_on(async move { store.head(&path).await }) {
            Ok(meta) => Ok(Some(meta.size)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.error(file, e)),
        }
    }

    /// The whole of `file`.
    pub(crate) fn read(&self, file: &str) -> Result<Vec<u8>, StoreError> {
        let (store, path) = (self.store.clone(), self.path(file));
        let got = block_on(async move {
            let r = store.get(&path).await?;
            let size = r.meta.size;
            let bytes = r.bytes().await?;
            Ok::<_, object_store::Error>((size, bytes))
        });
        match got {
            Ok((size, bytes)) if bytes.len() as u64 == size => Ok(bytes.to_vec()),
            Ok((size, bytes)) => Err(StoreError::Object {
                path: self.location.name(file),
                reason: format!("{} bytes came of the object's {size}", bytes.len()),
            }),
            Err(e) => Err(self.error(file, e)),
        }
    }

    /// Byte ranges of `file`: neighbouring ranges (closer than [`COALESCE_GAP`]) fetched as one
    /// request, the requests concurrently ([`Self::read_many`], with its checks and retries).
    pub(crate) fn read_ranges(
        &self,
        file: &str,
        ranges: &[Range<u64>],
    ) -> Result<Vec<Vec<u8>>, StoreError> {
        let (merged, which) = coalesce(ranges);
        let want: Vec<_> = merged.iter().map(|m| (file, m.clone())).collect();
        let got = self.read_many(&want)?;
        Ok(ranges
            .iter()
            .zip(which)
            .map(|(r, k)| {
                let m = &merged[k];
                got[k][(r.start - m.start) as usize..(r.end - m.start) as usize].to_vec()
            })
            .collect())
    }

    /// Ranges of several objects at once (one round trip's worth of concurrent requests). A body
    /// of another length than asked (cut short), or a request that failed after
    /// `object_store`'s own retries (a body cut off mid-way is not one of those), is asked for
    /// again, up to [`SHORT_READ_RETRIES`] times; a missing object or a refusal is not.
    pub(crate) fn read_many(
        &self,
        want: &[(&str, Range<u64>)],
    ) -> Result<Vec<Vec<u8>>, StoreError> {
        let mut out: Vec<Option<Vec<u8>>> = vec![None; want.len()];
        for attempt in 0..=SHORT_READ_RETRIES {
            let todo: Vec<usize> = (0..want.len()).filter(|&i| out[i].is_none()).collect();
            if todo.is_empty() {
                break;
            }
            let jobs: Vec<_> = todo
                .iter()
                .map(|&i| (i, self.path(want[i].0), want[i].1.clone()))
                .collect();
            let store = self.store.clone();
            let got = block_on(async move {
                let mut set = tokio::task::JoinSet::new();
                for (i, path, r) in jobs {
                    let store = store.clone();
                    set.spawn(async move { (i, store.get_range(&path, r).await) });
                }
                let mut got = Vec::new();
                while let Some(j) = set.join_next().await {
                    got.push(j.map_err(|e| object_store::Error::Generic {
                        store: "tetwave",
                        source: Box::new(e),
                    })?);
                }
                Ok(got)
            })
            .map_err(|e| self.error(want[0].0, e))?;
            let last = attempt == SHORT_READ_RETRIES;
            for (i, b) in got {
                let (file, r) = (want[i].0, &want[i].1);
                match b {
                    Ok(b) if b.len() as u64 == r.end - r.start => out[i] = Some(b.to_vec()),
                    Ok(b) if last => {
                        return Err(StoreError::Object {
                            path: self.location.name(file),
                            reason: format!(
                                "bytes {}..{}: {} came, {} times short",
                                r.start,
                                r.end,
                                b.len(),
                                SHORT_READ_RETRIES + 1
                            ),
                        })
                    }
                    Ok(_) => {}
                    Err(
                        e @ (object_store::Error::NotFound { .. }
                        | object_store::Error::PermissionDenied { .. }
                        | object_store::Error::Unauthenticated { .. }),
                    ) => return Err(self.error(file, e)),
                    Err(e) if last => return Err(self.error(file, e)),
                    Err(e) => tracing::warn!(
                        object = %self.location.name(file).display(),
                        "{e}: asking again"
                    ),
                }
            }
        }
        Ok(out
            .into_iter()
            .map(|b| b.expect("every range came"))
            .collect())
    }

    /// Writes `file` whole from the local file `from`: in parts of 16 MiB (multipart) when it
    /// is larger, in one request otherwise. The object appears only once written whole.
    pub(crate) fn upload(&self, file: &str, from: &Path) -> Result<(), StoreError> {
        const PART: usize = 16 << 20;
        let (store, path, from_path) = (self.store.clone(), self.path(file), from.to_path_buf());
        let len = std::fs::metadata(from).map_err(crate::io_err(from))?.len();
        let io = |e: std::io::Error| StoreError::Io {
            path: from.to_path_buf(),
            source: e,
        };
        if len <= PART as u64 {
            let bytes = std::fs::read(from).map_err(io)?;
            return block_on(async move { store.put(&path, bytes.into()).await })
                .map(|_| ())
                .map_err(|e| self.error(file, e));
        }
        let mut f = std::fs::File::open(&from_path).map_err(io)?;
        // the local file's errors inside, the object store's outside
        let r = block_on(async move {
            use std::io::Read;
            let u = store.put_multipart(&path).await?;
            let mut w = object_store::WriteMultipart::new_with_chunk_size(u, PART);
            let mut buf = vec![0u8; PART];
            loop {
                let n = match f.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => n,
                    Err(e) => {
                        w.abort().await?;
                        return Ok(Err(e));
                    }
                };
                w.wait_for_capacity(4).await?;
                w.write(&buf[..n]);
            }
            w.finish().await?;
            Ok(Ok(()))
        });
        r.map_err(|e| self.error(file, e))?.map_err(io)
    }

    /// Copies `file` into the local file `to`, in pieces of 16 MiB; `Ok(false)` when there is no
    /// such object.
    pub(crate) fn download(&self, file: &str, to: &Path) -> Result<bool, StoreError> {
        use std::io::Write;
        let Some(len) = self.size(file)? else {
            return Ok(false);
        };
        let mut f = std::fs::File::create(to).map_err(crate::io_err(to))?;
        let mut at = 0;
        while at < len {
            let end = (at + (16 << 20)).min(len);
            let got = self.read_ranges(file, std::slice::from_ref(&(at..end)))?;
            f.write_all(&got[0]).map_err(crate::io_err(to))?;
            at = end;
        }
        f.sync_all().map_err(crate::io_err(to))?;
        Ok(true)
    }

    /// Removes `file` (absent is fine).
    pub(crate) fn delete(&self, file: &str) -> Result<(), StoreError> {
        let (store, path) = (self.store.clone(), self.path(file));
        match block_on(async move { store.delete(&path).await }) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(self.error(file, e)),
        }
    }
}

/// A store's files wherever they are: what the reader and its checks read through.
#[derive(Clone, Debug)]
pub(crate) enum Files {
    Dir(PathBuf),
    Objects(Objects),
}

impl Files {
    pub(crate) fn open(location: &Location) -> Result<Files, StoreError> {
        Ok(match location {
            Location::Dir(d) => Files::Dir(d.clone()),
            remote => Files::Objects(Objects::connect(remote)?),
        })
    }

    /// What errors call `file`.
    pub(crate) fn name(&self, file: &str) -> PathBuf {
        match self {
            Files::Dir(d) => d.join(file),
            Files::Objects(o) => o.location.name(file),
        }
    }

    /// `file`'s size, or `None` when it is absent.
    pub(crate) fn size(&self, file: &str) -> Result<Option<u64>, StoreError> {
        match self {
            Files::Dir(d) => {
                let p = d.join(file);
                match std::fs::metadata(&p) {
                    Ok(m) => Ok(Some(m.len())),
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
                    Err(e) => Err(crate::io_err(&p)(e)),
                }
            }
            Files::Objects(o) => o.size(file),
        }
    }

    /// The whole of `file`.
    pub(crate) fn read(&self, file: &str) -> Result<Vec<u8>, StoreError> {
        match self {
            Files::Dir(d) => {
                let p = d.join(file);
                std::fs::read(&p).map_err(crate::io_err(&p))
            }
            Files::Objects(o) => o.read(file),
        }
    }

    /// Byte ranges of `file` (exactly, or an error).
    pub(crate) fn read_ranges(
        &self,
        file: &str,
        ranges: &[Range<u64>],
    ) -> Result<Vec<Vec<u8>>, StoreError> {
        match self {
            Files::Dir(d) => {
                use std::io::{Read, Seek, SeekFrom};
                let p = d.join(file);
                let mut f = std::fs::File::open(&p).map_err(crate::io_err(&p))?;
                ranges
                    .iter()
                    .map(|r| {
                        let mut buf = vec![0u8; (r.end - r.start) as usize];
                        f.seek(SeekFrom::Start(r.start))
                            .and_then(|_| f.read_exact(&mut buf))
                            .map_err(crate::io_err(&p))?;
                        Ok(buf)
                    })
                    .collect()
            }
            Files::Objects(o) => o.read_ranges(file, ranges),
        }
    }
}

impl Files {
    /// One byte range of `file`.
    pub(crate) fn read_range(&self, file: &str, r: Range<u64>) -> Result<Vec<u8>, StoreError> {
        Ok(self.read_ranges(file, std::slice::from_ref(&r))?.remove(0))
    }

    /// Ranges of several files, concurrently where they are objects.
    pub(crate) fn read_many(
        &self,
        want: &[(&str, Range<u64>)],
    ) -> Result<Vec<Vec<u8>>, StoreError> {
        match self {
            Files::Objects(o) => o.read_many(want),
            Files::Dir(_) => want
                .iter()
                .map(|(f, r)| self.read_range(f, r.clone()))
                .collect(),
        }
    }
}

impl tetwave_protocol::store_format::StoreFiles for Files {
    type Error = StoreError;
    fn read_at(&self, file: &str, offset: u64, buf: &mut [u8]) -> Result<(), StoreError> {
        buf.copy_from_slice(&self.read_range(file, offset..offset + buf.len() as u64)?);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `Objects` over an in-memory object store holding `bytes` as `f`.
    fn in_memory(bytes: &[u8]) -> Objects {
        let store: Arc<dyn ObjectStore> = Arc::new(object_store::memory::InMemory::new());
        let (s, data) = (store.clone(), bytes.to_vec());
        block_on(async move { s.put(&ObjectPath::from("p/f"), data.into()).await }).unwrap();
        Objects {
            store,
            prefix: "p".into(),
            location: Location::parse("s3://b/p").unwrap(),
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// Coalesced ranges (unsorted, overlapping, adjacent, far apart) read back exactly the
        /// bytes asked for, in the order asked.
        #[test]
        fn coalesced_ranges_read_back_exactly(
            len in 1u64..300_000,
            picks in proptest::collection::vec((0u64..300_000, 0u64..100_000), 1..12),
        ) {
            let bytes: Vec<u8> = (0..len).map(|i| (i * 2654435761 % 251) as u8).collect();
            let o = in_memory(&bytes);
            let ranges: Vec<Range<u64>> = picks
                .iter()
                .map(|&(a, n)| {
                    let a = a % len;
                    a..(a + n).min(len)
                })
                .collect();
            let got = o.read_ranges("f", &ranges).unwrap();
            for (r, g) in ranges.iter().zip(&got) {
                proptest::prop_assert_eq!(&g[..], &bytes[r.start as usize..r.end as usize]);
            }
        }
    }

    #[test]
    fn a_range_past_the_end_or_a_missing_object_is_an_error_naming_it() {
        let o = in_memory(b"0123456789");
        let e = o
            .read_ranges("f", std::slice::from_ref(&(5..20)))
            .unwrap_err()
            .to_string();
        assert!(e.contains("s3://b/p/f"), "{e}");
        let e = o.read("g").unwrap_err().to_string();
        assert!(e.contains("s3://b/p/g"), "{e}");
        assert_eq!(o.size("g").unwrap(), None);
        assert_eq!(o.size("f").unwrap(), Some(10));
    }

    #[test]
    fn what_a_user_types_is_a_path_a_bucket_or_a_folder() {
        assert_eq!(
            Location::parse("out/torus").unwrap(),
            Location::Dir("out/torus".into())
        );
        let s3 = Location::parse("s3://b/stores//torus/").unwrap();
        assert_eq!(
            s3,
            Location::S3 {
                bucket: "b".into(),
                prefix: "stores/torus".into()
            }
        );
        assert_eq!(s3.to_string(), "s3://b/stores/torus");
        assert_eq!(
            s3.name("blocks.bin"),
            PathBuf::from("s3://b/stores/torus/blocks.bin")
        );
        assert_eq!(
            s3.join("parts/part-0-of-2").to_string(),
            "s3://b/stores/torus/parts/part-0-of-2"
        );
        let h = Location::parse("http://127.0.0.1:8080/s/t").unwrap();
        assert_eq!(
            h,
            Location::Http {
                root: "http://127.0.0.1:8080".into(),
                prefix: "s/t".into()
            }
        );
        assert_eq!(
            Location::parse("s3://bucket").unwrap().to_string(),
            "s3://bucket"
        );
        for bad in [
            "s3://",
            "s3:///x",
            "http://",
            "https:///x",
            "ftp://x/y",
            "http://h/x?y=1",
        ] {
            assert!(
                matches!(Location::parse(bad), Err(StoreError::Location { .. })),
                "{bad}"
            );
        }
    }
}
