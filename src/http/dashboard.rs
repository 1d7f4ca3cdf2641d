//! The web dashboard: one static page (`GET /`) and its script, style sheet and icon
//! (`GET /ui/{file}`), compiled into the binary from `src/http/dashboard/`. Plain HTML, CSS
//! and JavaScript with no build step and no third-party code; nothing is fetched from
//! anywhere but the daemon itself, so it works in an air-gapped farm.
//!
//! The shell is open to anyone, like the probes: it holds no data. Everything the page
//! shows comes from the authenticated API (`/v1/...`), which the script calls with
//! `Authorization: Bearer` and the token the user typed, kept in the tab's
//! `sessionStorage` (never in a URL, a cookie or `localStorage`). Event streams are read
//! with `fetch` and a stream reader, since `EventSource` cannot send that header.
//!
//! Every answer carries a Content-Security-Policy that allows scripts, styles, images and
//! connections from the daemon's own origin only (images also from `blob:` URLs, which is
//! how the page shows previews it fetched with the token), no inline script or style, no
//! framing; plus `nosniff` and `no-referrer`. Assets are revalidated on each load (ETag),
//! so a new binary's page is picked up at once.

use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use sha2::{Digest, Sha256};

use super::{ApiError, AppState};
use crate::error::Error;

/// The dashboard's routes, open without a token (see the module docs). Kept apart from
/// the API's tables: they are not API operations and are not in the OpenAPI document.
pub const DASHBOARD_ROUTES: &[(&str, &str)] = &[("GET", "/"), ("GET", "/ui/{file}")];

/// The policy every dashboard answer carries.
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
     img-src 'self' blob:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// A file of the page.
struct Asset {
    name: &'static str,
    content_type: &'static str,
    body: &'static [u8],
}

const INDEX: Asset = Asset {
    name: "index.html",
    content_type: "text/html; charset=utf-8",
    body: include_bytes!("dashboard/index.html"),
};

/// What `/ui/{file}` serves.
const ASSETS: &[Asset] = &[
    Asset { name: "app.js", content_type: "text/javascript; charset=utf-8", body: include_bytes!("dashboard/app.js") },
    Asset { name: "app.css", content_type: "text/css; charset=utf-8", body: include_bytes!("dashboard/app.css") },
    Asset { name: "icon.svg", content_type: "image/svg+xml", body: include_bytes!("dashboard/icon.svg") },
];

/// The names of every file of the page (for tests: each is checked for outside URLs).
pub fn asset_names() -> impl Iterator<Item = &'static str> {
    std::iter::once(INDEX.name).chain(ASSETS.iter().map(|a| a.name))
}

/// The bytes of the file `name` of the page.
pub fn asset(name: &str) -> Option<&'static [u8]> {
    std::iter::once(&INDEX).chain(ASSETS).find(|a| a.name == name).map(|a| a.body)
}

pub(super) fn routes() -> Router<AppState> {
    Router::new().route("/", get(index)).route("/ui/{file}", get(file))
}

async fn index(headers: HeaderMap) -> Response {
    serve(&INDEX, &headers)
}

async fn file(axum::extract::Path(name): axum::extract::Path<String>, headers: HeaderMap) -> Response {
    match ASSETS.iter().find(|a| a.name == name) {
        Some(asset) => serve(asset, &headers),
        None => ApiError::from(Error::NotFound(format!(
            "no dashboard file {}",
            crate::error::truncate(&name, crate::error::ECHO_CHARS)
        )))
        .into_response(),
    }
}

/// The asset with the dashboard's headers; 304 when the client's copy is current.
fn serve(asset: &Asset, request: &HeaderMap) -> Response {
    let digest = Sha256::digest(asset.body);
    let etag: String = std::iter::once("\"".to_string())
        .chain(digest[..12].iter().map(|b| format!("{b:02x}")))
        .chain(std::iter::once("\"".to_string()))
        .collect();
    let fresh = request.get(header::IF_NONE_MATCH).and_then(|v| v.to_str().ok()).is_some_and(|v| {
        v.split(',').any(|t| {
            let t = t.trim();
            t == etag || t == "*"
        })
    });
    let mut response = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, asset.content_type)], asset.body).into_response()
    };
    let h = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CONTENT_SECURITY_POLICY));
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    response
}
