//! Host and Origin allowlists, against DNS rebinding and cross-site requests.
//!
//! - **Host**: a request whose `Host` names a host other than an IP literal, `localhost` (or a
//!   `*.localhost` name) or one of `--allow-host` is refused (403). A rebinding attack reaches a
//!   loopback server under the attacker's own domain name, which this refuses; IP literals cannot be
//!   rebound.
//! - **Origin**: a request with an `Origin` header (browsers send one on WebSocket upgrades and
//!   cross-origin fetches) is refused unless the origin is this server's own (`http://` + the
//!   request's `Host`) or one of `--allow-origin` (`*`: any).
//! - **Fetch metadata**: a browser request marked `Sec-Fetch-Site: cross-site` or `same-site` without
//!   an allowed `Origin` is refused (an `<img>` on another site must not start a render), except a
//!   top-level navigation to the viewer page `/`.
//!
//! Clients that are not browsers send neither `Origin` nor `Sec-Fetch-*` and pass.

use super::state::Shared;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::sync::Arc;

/// The allowlists.
#[derive(Debug, Clone, Default)]
pub struct OriginPolicy {
    /// Host names allowed besides IP literals and `localhost` (`*`: any), lowercase.
    pub allow_hosts: Vec<String>,
    /// Origins allowed besides the server's own, as `scheme://host[:port]` (`*`: any), lowercase.
    pub allow_origins: Vec<String>,
}

/// The host part of a `Host` header value (`name`, `1.2.3.4`, `[::1]`), lowercase, port removed.
fn host_name(host: &str) -> String {
    let h = host.trim().to_ascii_lowercase();
    if let Some(rest) = h.strip_prefix('[') {
        return rest.split(']').next().unwrap_or("").to_string();
    }
    match h.rsplit_once(':') {
        Some((name, port)) if port.chars().all(|c| c.is_ascii_digit()) => name.to_string(),
        _ => h,
    }
}

impl OriginPolicy {
    fn host_allowed(&self, host: &str) -> bool {
        let name = host_name(host);
        name.parse::<std::net::IpAddr>().is_ok()
            || name == "localhost"
            || name.ends_with(".localhost")
            || self.allow_hosts.iter().any(|a| a == "*" || *a == name)
    }

    fn origin_allowed(&self, origin: &str, host: Option<&str>) -> bool {
        let o = origin.trim().to_ascii_lowercase();
        if self.allow_origins.iter().any(|a| a == "*" || *a == o) {
            return true;
        }
        host.is_some_and(|h| o == format!("http://{}", h.trim().to_ascii_lowercase()))
    }

    /// `Err(why)` when the request must be refused.
    pub fn check(&self, headers: &HeaderMap, path: &str) -> Result<(), String> {
        let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
        if let Some(h) = host {
            if !self.host_allowed(h) {
                return Err(format!(
                    "Host {h:?} is not allowed (start the server with --allow-host {} to serve it)",
                    host_name(h)
                ));
            }
        }
        let origin = headers
            .get(header::ORIGIN)
            .map(|v| v.to_str().unwrap_or("?"));
        if let Some(o) = origin {
            if !self.origin_allowed(o, host) {
                return Err(format!(
                    "Origin {o:?} is not allowed (start the server with --allow-origin {o} to allow it)"
                ));
            }
            return Ok(());
        }
        let site = headers.get("sec-fetch-site").and_then(|v| v.to_str().ok());
        if matches!(site, Some("cross-site" | "same-site")) {
            let navigate = headers
                .get("sec-fetch-mode")
                .is_some_and(|m| m.as_bytes() == b"navigate");
            if !(navigate && path == "/") {
                return Err("a cross-site request without an allowed Origin".into());
            }
        }
        Ok(())
    }
}

pub(super) async fn check_origin(
    State(s): State<Arc<Shared>>,
    req: Request,
    next: Next,
) -> Response {
    if let Err(why) = s.config.origins.check(req.headers(), req.uri().path()) {
        tracing::warn!(path = req.uri().path(), "refused: {why}");
        return (StatusCode::FORBIDDEN, format!("{why}\n")).into_response();
    }
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn headers(pairs: &[(&str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(
                axum::http::HeaderName::from_bytes(k.as_bytes()).unwrap(),
                HeaderValue::from_str(v).unwrap(),
            );
        }
        h
    }

    #[test]
    fn hosts() {
        let p = OriginPolicy::default();
        for ok in [
            "127.0.0.1:7878",
            "localhost:1",
            "[::1]:80",
            "LOCALHOST",
            "a.localhost",
            "10.0.0.2",
        ] {
            assert!(p.check(&headers(&[("host", ok)]), "/").is_ok(), "{ok}");
        }
        for bad in [
            "evil.example",
            "evil.example:7878",
            "localhost.evil.example",
        ] {
            assert!(p.check(&headers(&[("host", bad)]), "/").is_err(), "{bad}");
        }
        let p = OriginPolicy {
            allow_hosts: vec!["viz.lab".into()],
            ..Default::default()
        };
        assert!(p.check(&headers(&[("host", "viz.lab:7878")]), "/").is_ok());
    }

    #[test]
    fn origins() {
        let p = OriginPolicy::default();
        let h = |o: &str| headers(&[("host", "127.0.0.1:7878"), ("origin", o)]);
        assert!(p.check(&h("http://127.0.0.1:7878"), "/v1/stream").is_ok());
        for bad in [
            "http://evil.example",
            "http://127.0.0.1:9999",
            "null",
            "https://127.0.0.1:7878",
        ] {
            assert!(p.check(&h(bad), "/v1/stream").is_err(), "{bad}");
        }
        let p = OriginPolicy {
            allow_origins: vec!["http://viz.lab".into()],
            ..Default::default()
        };
        assert!(p.check(&h("http://viz.lab"), "/v1/stream").is_ok());
    }

    #[test]
    fn cross_site_fetches() {
        let p = OriginPolicy::default();
        let h = |site: &str, mode: &str| {
            headers(&[
                ("host", "127.0.0.1:7878"),
                ("sec-fetch-site", site),
                ("sec-fetch-mode", mode),
            ])
        };
        assert!(p.check(&h("cross-site", "no-cors"), "/v1/render").is_err());
        assert!(p.check(&h("same-site", "no-cors"), "/v1/render").is_err());
        assert!(p.check(&h("same-origin", "no-cors"), "/v1/render").is_ok());
        assert!(p.check(&h("none", "navigate"), "/v1/render").is_ok());
        assert!(p.check(&h("cross-site", "navigate"), "/").is_ok());
        assert!(p.check(&h("cross-site", "navigate"), "/v1/render").is_err());
    }
}
