//! The token: required from every client when configured, given as `Authorization: Bearer T` (the
//! scheme in any case), as `?token=T`, or (on the stream) in `Hello.token`.
//!
//! Comparison takes time that depends on neither the guess's content nor its length relative to the
//! token (both sides are hashed with a per-process random key first). Wrong tokens are logged with the
//! peer's address and rate-limited per peer address: [`FAIL_BURST`] attempts, then one per
//! [`FAIL_REFILL`]; beyond that a peer gets 429 with `Retry-After`, right token or not.

use super::admission::Peer;
use super::state::Shared;
use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::collections::HashMap;
use std::hash::{BuildHasher, RandomState};
use std::net::IpAddr;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// Wrong tokens a peer may send in a burst.
pub const FAIL_BURST: f64 = 10.0;
/// … after which it may try once per this long.
pub const FAIL_REFILL: Duration = Duration::from_secs(1);
/// Peers remembered at most (the table is pruned, then cleared, beyond it).
const MAX_PEERS: usize = 4096;

/// Whether `given` is the token `want`, in time independent of where they differ and of `given`'s
/// length relative to `want`'s: keyed hashes are compared first, the strings only when those agree.
pub(super) fn same(given: &str, want: &str) -> bool {
    static KEY: OnceLock<RandomState> = OnceLock::new();
    let key = KEY.get_or_init(RandomState::new);
    let (hg, hw) = (
        key.hash_one(given.as_bytes()),
        key.hash_one(want.as_bytes()),
    );
    // no early exit on the hashes; the string comparison runs only on a (near-)certain match
    ((hg ^ hw) == 0) & (given == want)
}

/// The token in an `Authorization` header value: `Bearer T`, scheme case-insensitive.
pub(super) fn bearer(v: &HeaderValue) -> Option<&str> {
    let (scheme, t) = v.to_str().ok()?.trim().split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then(|| t.trim())
}

/// Per-peer budget of wrong tokens (a token bucket per address).
#[derive(Default)]
pub struct FailureLimiter {
    peers: Mutex<HashMap<IpAddr, (f64, Instant)>>,
}

impl FailureLimiter {
    fn level(entry: &(f64, Instant), now: Instant) -> f64 {
        (entry.0 + (now - entry.1).as_secs_f64() / FAIL_REFILL.as_secs_f64()).min(FAIL_BURST)
    }

    /// `Err(wait)` while `ip` has no attempts left.
    pub fn check(&self, ip: IpAddr) -> Result<(), Duration> {
        let peers = self.peers.lock().unwrap_or_else(|e| e.into_inner());
        match peers.get(&ip) {
            Some(e) => {
                let level = Self::level(e, Instant::now());
                if level >= 1.0 {
                    Ok(())
                } else {
                    Err(FAIL_REFILL.mul_f64(1.0 - level))
                }
            }
            None => Ok(()),
        }
    }

    /// Records a wrong token from `peer` and logs it.
    pub fn failed(&self, peer: Option<std::net::SocketAddr>, what: &str) {
        let ip = peer.map_or(IpAddr::from([0, 0, 0, 0]), |p| p.ip());
        let now = Instant::now();
        let mut peers = self.peers.lock().unwrap_or_else(|e| e.into_inner());
        if peers.len() >= MAX_PEERS && !peers.contains_key(&ip) {
            peers.retain(|_, e| Self::level(e, now) < FAIL_BURST);
            if peers.len() >= MAX_PEERS {
                peers.clear();
            }
        }
        let e = peers.entry(ip).or_insert((FAIL_BURST, now));
        *e = (Self::level(e, now) - 1.0, now);
        let left = e.0.max(0.0);
        drop(peers);
        match peer {
            Some(p) => tracing::warn!(peer = %p, left, "{what}: wrong token"),
            None => tracing::warn!(left, "{what}: wrong token"),
        }
    }
}

/// The token a request carries: `Authorization: Bearer T` or `?token=T`.
fn request_token(headers: &HeaderMap, uri: &axum::http::Uri) -> Option<String> {
    if let Some(v) = headers.get(header::AUTHORIZATION) {
        return bearer(v).map(str::to_string);
    }
    let q: Query<HashMap<String, String>> = Query::try_from_uri(uri).ok()?;
    q.0.get("token").cloned()
}

pub(super) async fn require_token(
    State(s): State<Arc<Shared>>,
    req: Request,
    next: Next,
) -> Response {
    if let Some(want) = &s.config.token {
        let peer = req.extensions().get::<Peer>().map(|p| p.0);
        if let Some(p) = peer {
            if let Err(wait) = s.auth_failures.check(p.ip()) {
                return too_many(wait);
            }
        }
        match request_token(req.headers(), req.uri()) {
            Some(t) if same(&t, want) => {}
            Some(_) => {
                s.auth_failures.failed(peer, req.uri().path());
                return unauthorized();
            }
            None => return unauthorized(),
        }
    }
    next.run(req).await
}

fn unauthorized() -> Response {
    (
        StatusCode::UNAUTHORIZED,
        [(header::WWW_AUTHENTICATE, "Bearer")],
        "missing or wrong token\n",
    )
        .into_response()
}

/// 429 with `Retry-After` (whole seconds, at least 1).
pub(super) fn too_many(wait: Duration) -> Response {
    let secs = wait.as_secs_f64().ceil().max(1.0) as u64;
    (
        StatusCode::TOO_MANY_REQUESTS,
        [(header::RETRY_AFTER, secs.to_string())],
        "too many wrong tokens from this address; try again later\n",
    )
        .into_response()
}

/// Why a stream upgrade request is refused.
pub(super) enum Refused {
    Unauthorized,
    TooMany(Duration),
}

impl IntoResponse for Refused {
    fn into_response(self) -> Response {
        match self {
            Refused::Unauthorized => unauthorized(),
            Refused::TooMany(w) => too_many(w),
        }
    }
}

/// Whether a stream upgrade request is already authenticated: `Ok(true)` when no token is configured
/// or the request carries the right one, `Ok(false)` when it carries none (`Hello` must then carry
/// it), [`Refused`] when it carries a wrong one or its peer is out of attempts.
pub(super) fn upgrade_auth(
    s: &Shared,
    peer: Option<std::net::SocketAddr>,
    headers: &HeaderMap,
    query_token: Option<&String>,
) -> Result<bool, Refused> {
    let Some(want) = &s.config.token else {
        return Ok(true);
    };
    if let Some(p) = peer {
        s.auth_failures.check(p.ip()).map_err(Refused::TooMany)?;
    }
    let given = match headers.get(header::AUTHORIZATION) {
        Some(h) => bearer(h),
        None => query_token.map(String::as_str),
    };
    match given {
        None => Ok(false),
        Some(t) if same(t, want) => Ok(true),
        Some(_) => {
            s.auth_failures.failed(peer, "/v1/stream");
            Err(Refused::Unauthorized)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_compares_whole_strings() {
        assert!(same("s3cret", "s3cret"));
        assert!(!same("s3cre", "s3cret"));
        assert!(!same("s3cret!", "s3cret"));
        assert!(!same("", "s3cret"));
        assert!(!same("S3cret", "s3cret"));
    }

    #[test]
    fn bearer_scheme_is_case_insensitive() {
        for v in ["Bearer abc", "bearer abc", "BEARER  abc ", "  bEaReR abc"] {
            assert_eq!(
                bearer(&HeaderValue::from_str(v).unwrap()),
                Some("abc"),
                "{v:?}"
            );
        }
        assert_eq!(bearer(&HeaderValue::from_static("Basic abc")), None);
        assert_eq!(bearer(&HeaderValue::from_static("Bearer")), None);
    }

    #[test]
    fn failures_run_out_then_refill() {
        let l = FailureLimiter::default();
        let ip: IpAddr = [127, 0, 0, 9].into();
        let peer = Some(std::net::SocketAddr::new(ip, 1));
        for _ in 0..FAIL_BURST as usize {
            assert!(l.check(ip).is_ok());
            l.failed(peer, "test");
        }
        let wait = l.check(ip).expect_err("out of attempts");
        assert!(wait <= FAIL_REFILL);
        // another address is not affected
        assert!(l.check([127, 0, 0, 10].into()).is_ok());
        std::thread::sleep(wait + Duration::from_millis(20));
        assert!(l.check(ip).is_ok(), "one attempt back after {wait:?}");
    }
}
