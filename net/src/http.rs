//! Plain HTTP GETs of the server's routes beside the stream (`/v1/render`, `/v1/levelset`), with
//! the stream's token.

use crate::error::HttpError;
use std::time::Duration;

/// The body of `GET url` (at most `limit` bytes, within `timeout` all told), sending `token` as a
/// bearer token when given; an error names the URL.
pub fn get(
    url: &str,
    token: Option<&str>,
    limit: u64,
    timeout: Duration,
) -> Result<Vec<u8>, HttpError> {
    let fail = |e: ureq::Error| HttpError {
        url: url.to_string(),
        reason: e.to_string(),
    };
    let mut req = ureq::get(url)
        .config()
        .timeout_global(Some(timeout))
        .build();
    if let Some(t) = token {
        req = req.header("Authorization", &format!("Bearer {t}"));
    }
    let mut resp = req.call().map_err(fail)?;
    resp.body_mut()
        .with_config()
        .limit(limit)
        .read_to_vec()
        .map_err(fail)
}
