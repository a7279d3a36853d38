//! The token: required from every client when configured, given as `Authorization: Bearer T`, as
//! `?token=T`, or (on the stream) in `Hello.token`; compared in constant time.

use super::state::Shared;
use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::collections::HashMap;
use std::sync::Arc;

/// Constant-time string equality (the token check must not leak a prefix by timing).
pub(super) fn same(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The token a request carries: `Authorization: Bearer T` or `?token=T`.
fn request_token(headers: &HeaderMap, uri: &axum::http::Uri) -> Option<String> {
    if let Some(v) = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
    {
        if let Some(t) = v.strip_prefix("Bearer ") {
            return Some(t.trim().to_string());
        }
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
        let ok = request_token(req.headers(), req.uri()).is_some_and(|t| same(&t, want));
        if !ok {
            return unauthorized();
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

/// A request carried a wrong token; answers 401.
pub(super) struct Unauthorized;

impl IntoResponse for Unauthorized {
    fn into_response(self) -> Response {
        unauthorized()
    }
}

/// Whether a stream upgrade request is already authenticated: `Ok(true)` when no token is configured
/// or the request carries the right one, `Ok(false)` when it carries none (`Hello` must then carry
/// it), [`Unauthorized`] when it carries a wrong one.
pub(super) fn upgrade_auth(
    want: Option<&String>,
    headers: &HeaderMap,
    query_token: Option<&String>,
) -> Result<bool, Unauthorized> {
    match (want, headers.get(header::AUTHORIZATION), query_token) {
        (None, ..) => Ok(true),
        (Some(want), Some(h), _) => match h.to_str().ok().and_then(|v| v.strip_prefix("Bearer ")) {
            Some(t) if same(t.trim(), want) => Ok(true),
            _ => Err(Unauthorized),
        },
        (Some(want), None, Some(t)) => {
            if !same(t, want) {
                return Err(Unauthorized);
            }
            Ok(true)
        }
        (Some(_), None, None) => Ok(false),
    }
}
