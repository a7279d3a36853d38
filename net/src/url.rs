//! The one home of a server's addresses: what the user typed (`http://host:port` or
//! `ws://host:port`, with or without a path) becomes a [`ServerUrl`], and every route the client
//! uses is built from it, never by editing another route's string.

use crate::error::NetError;

/// A `tetwave-server serve` address: its host and port (`host:port`, or `host` alone).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ServerUrl {
    host: String,
}

impl ServerUrl {
    /// Parses `http://host[:port][/path]` or `ws://host[:port][/path]` (the path is ignored: the
    /// routes are the protocol's).
    pub fn parse(url: &str) -> Result<ServerUrl, NetError> {
        let rest = url
            .strip_prefix("http://")
            .or_else(|| url.strip_prefix("ws://"))
            .ok_or_else(|| NetError::Url(url.into()))?;
        let host = rest.split(['/', '?', '#']).next().unwrap_or("");
        if host.is_empty() || host.contains(char::is_whitespace) {
            return Err(NetError::Url(url.into()));
        }
        Ok(ServerUrl { host: host.into() })
    }

    /// Whether `s` names a server (rather than a path).
    pub fn is_server(s: &str) -> bool {
        s.starts_with("http://") || s.starts_with("ws://")
    }

    /// `host:port`.
    pub fn host(&self) -> &str {
        &self.host
    }

    /// The HTTP root, `http://host:port`.
    pub fn http(&self) -> String {
        format!("http://{}", self.host)
    }

    /// The WebSocket stream, `ws://host:port/v1/stream`, asking for the view order under
    /// transfer function `tf` when given (`?tf=auto`).
    pub fn stream(&self, tf: Option<&str>) -> String {
        match tf {
            Some(tf) => format!("ws://{}/v1/stream?tf={tf}", self.host),
            None => format!("ws://{}/v1/stream", self.host),
        }
    }

    /// The near band of the domain's level set, `GET /v1/levelset`.
    pub fn levelset(&self) -> String {
        format!("{}/v1/levelset", self.http())
    }

    /// The server's image of a view, `GET /v1/render?{query}`.
    pub fn render(&self, query: &str) -> String {
        format!("{}/v1/render?{query}", self.http())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_come_from_the_host_whatever_was_typed() {
        for typed in [
            "http://127.0.0.1:8080",
            "ws://127.0.0.1:8080/v1/stream",
            "http://127.0.0.1:8080/",
            "http://127.0.0.1:8080/v1/render?w=3",
        ] {
            let u = ServerUrl::parse(typed).unwrap();
            assert_eq!(u.host(), "127.0.0.1:8080", "{typed}");
            assert_eq!(u.stream(None), "ws://127.0.0.1:8080/v1/stream");
            assert_eq!(
                u.stream(Some("auto")),
                "ws://127.0.0.1:8080/v1/stream?tf=auto"
            );
            assert_eq!(u.levelset(), "http://127.0.0.1:8080/v1/levelset");
            assert_eq!(u.render("a=1"), "http://127.0.0.1:8080/v1/render?a=1");
        }
    }

    #[test]
    fn anything_else_is_refused() {
        for bad in [
            "",
            "127.0.0.1:8080",
            "https://x",
            "http://",
            "ws:///v1/stream",
            "http://a b",
        ] {
            assert!(
                matches!(ServerUrl::parse(bad), Err(NetError::Url(_))),
                "{bad}"
            );
        }
    }
}
