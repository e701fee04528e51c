//! Requests to the Hub over `ureq`, redirects followed by hand: the token goes only to the Hub's own origin
//! (scheme, host and port of the endpoint), never to the host an LFS file is redirected to.

use std::time::Duration;

/// A response: status, headers (names lower-case) and, for GET, the body.
pub(crate) struct Resp {
    pub status: u16,
    pub url: String,
    headers: Vec<(String, String)>,
    pub body: Option<ureq::Body>,
}

impl Resp {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_str())
    }

    pub fn is_redirect(&self) -> bool {
        matches!(self.status, 301 | 302 | 303 | 307 | 308)
    }
}

/// Which redirects a request follows.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Follow {
    /// Only those to the same origin (relative ones included); a redirect elsewhere is returned as is — the
    /// metadata request, as Python's `_httpx2_follow_hub_redirects…`.
    SameOrigin,
    /// All of them (the download).
    All,
}

pub(crate) struct Http {
    agent: ureq::Agent,
    endpoint: String,
    token: Option<String>,
}

impl Http {
    pub fn new(endpoint: &str, token: Option<String>) -> Self {
        let config = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .max_redirects(0)
            .user_agent(concat!("mvsplat360-hub/", env!("CARGO_PKG_VERSION")))
            .accept_encoding("identity")
            .timeout_connect(Some(Duration::from_secs(20)))
            .timeout_recv_response(Some(Duration::from_secs(60)))
            .timeout_per_read(Some(Duration::from_secs(120)))
            .build();
        Self { agent: config.new_agent(), endpoint: endpoint.trim_end_matches('/').to_string(), token }
    }

    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    pub fn has_token(&self) -> bool {
        self.token.is_some()
    }

    /// One request (HEAD unless `get`), `Range: bytes=START-` when given, redirects as `follow` says.
    pub fn request(&self, get: bool, url: &str, range_start: Option<u64>, follow: Follow) -> Result<Resp, ureq::Error> {
        let mut url = url.to_string();
        for _ in 0..10 {
            let r = self.once(get, &url, range_start)?;
            if !r.is_redirect() {
                return Ok(r);
            }
            let Some(next) = r.header("location").map(|l| join(&url, l)) else { return Ok(r) };
            if follow == Follow::SameOrigin && origin(&next) != origin(&url) {
                return Ok(r);
            }
            url = next;
        }
        Err(ureq::Error::TooManyRedirects)
    }

    fn once(&self, get: bool, url: &str, range_start: Option<u64>) -> Result<Resp, ureq::Error> {
        let auth = self.token.as_ref().filter(|_| origin(url).is_some() && origin(url) == origin(&self.endpoint));
        let resp = if get {
            let mut req = self.agent.get(url);
            if let Some(t) = auth {
                req = req.header("Authorization", format!("Bearer {t}"));
            }
            if let Some(s) = range_start {
                req = req.header("Range", format!("bytes={s}-"));
            }
            req.call()?
        } else {
            let mut req = self.agent.head(url);
            if let Some(t) = auth {
                req = req.header("Authorization", format!("Bearer {t}"));
            }
            if let Some(s) = range_start {
                req = req.header("Range", format!("bytes={s}-"));
            }
            req.call()?
        };
        let (parts, body) = resp.into_parts();
        let headers = parts.headers.iter().filter_map(|(n, v)| Some((n.as_str().to_ascii_lowercase(), v.to_str().ok()?.to_string()))).collect();
        Ok(Resp { status: parts.status.as_u16(), url: url.to_string(), headers, body: get.then_some(body) })
    }

    /// GET a small JSON document (the repository's file list).
    pub fn get_json(&self, url: &str) -> Result<(Resp, Option<serde_json::Value>), ureq::Error> {
        let mut r = self.request(true, url, None, Follow::SameOrigin)?;
        if r.status != 200 {
            return Ok((r, None));
        }
        let text = r.body.take().expect("GET has a body").with_config().limit(64 << 20).read_to_string()?;
        Ok((r, serde_json::from_str(&text).ok()))
    }
}

/// `scheme://host[:port]` of a URL, lower-case; `None` when it is not absolute.
pub(crate) fn origin(url: &str) -> Option<String> {
    let (scheme, rest) = url.split_once("://")?;
    let host = rest.split(['/', '?', '#']).next()?;
    let host = host.rsplit_once('@').map_or(host, |(_, h)| h).to_ascii_lowercase();
    let scheme = scheme.to_ascii_lowercase();
    let host = match (scheme.as_str(), host.strip_suffix(":443"), host.strip_suffix(":80")) {
        ("https", Some(h), _) | ("http", _, Some(h)) => h.to_string(),
        _ => host,
    };
    Some(format!("{scheme}://{host}"))
}

/// A redirect's `Location` against the URL it answered.
pub(crate) fn join(base: &str, location: &str) -> String {
    if location.contains("://") {
        return location.to_string();
    }
    let scheme = base.split_once("://").map_or("https", |(s, _)| s);
    if let Some(rest) = location.strip_prefix("//") {
        return format!("{scheme}://{rest}");
    }
    let origin = origin(base).unwrap_or_default();
    if location.starts_with('/') {
        return format!("{origin}{location}");
    }
    let path = base.split_once("://").map_or("", |(_, r)| r);
    let path = path.find('/').map_or("/", |i| &path[i..]);
    let path = path.split(['?', '#']).next().unwrap_or("/");
    let dir = &path[..=path.rfind('/').unwrap_or(0)];
    format!("{origin}{dir}{location}")
}

/// `X-Error-Code`-aware classification of an HTTP error status, as Python's `hf_raise_for_status`.
pub(crate) fn error_code(r: &Resp) -> Option<&str> {
    r.header("x-error-code")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn origins_and_joins() {
        assert_eq!(origin("https://huggingface.co/a/b").as_deref(), Some("https://huggingface.co"));
        assert_eq!(origin("https://HuggingFace.co:443/a").as_deref(), Some("https://huggingface.co"));
        assert_ne!(origin("http://127.0.0.1:80/a"), origin("http://127.0.0.1:81/a"));
        assert_eq!(origin("relative/x"), None);
        assert_eq!(join("http://h:1/a/b/c?x=1", "/d/e"), "http://h:1/d/e");
        assert_eq!(join("http://h:1/a/b/c", "d"), "http://h:1/a/b/d");
        assert_eq!(join("http://h:1/a", "http://g:2/x"), "http://g:2/x");
        assert_eq!(join("https://h/a", "//cdn/x"), "https://cdn/x");
    }
}
