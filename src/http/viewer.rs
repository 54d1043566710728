//! The viewer: one page, its script and its style sheet, compiled into the binary and served
//! at `/` and `/viewer/*`. They hold no data, so they are open even when the service has a
//! token: the page asks for the token and sends it on each of its `/v1` calls.
//!
//! They are a page, not part of the API: `openapi.yaml` leaves them out (and so the contract
//! test does not fuzz them), and [`super::ROUTES`], which a test holds equal to that document,
//! does not list them.

use axum::Router;
use axum::http::{HeaderName, HeaderValue, header};
use axum::response::IntoResponse;
use axum::routing::get;

use super::AppState;

/// One file of the viewer.
#[derive(Debug, Clone, Copy)]
pub struct Asset {
    /// The path it is served at.
    pub path: &'static str,
    /// Its media type.
    pub content_type: &'static str,
    /// Its text.
    pub body: &'static str,
}

/// Every file of the viewer, the page first.
pub const ASSETS: &[Asset] = &[
    Asset { path: "/", content_type: "text/html; charset=utf-8", body: include_str!("viewer/index.html") },
    Asset {
        path: "/viewer/viewer.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_str!("viewer/viewer.js"),
    },
    Asset {
        path: "/viewer/viewer.css",
        content_type: "text/css; charset=utf-8",
        body: include_str!("viewer/viewer.css"),
    },
];

/// Only the viewer's own files run and are fetched; the API is same-origin. `data:` images are
/// the page's empty icon (without one the browser asks for `/favicon.ico`, a 404).
const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
     connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The routes of [`ASSETS`]. Each answers `GET` (and `HEAD`) with its file; other methods are
/// the router's 405 problem, like any route's.
pub fn routes() -> Router<AppState> {
    ASSETS.iter().fold(Router::new(), |router, asset| {
        let asset = *asset;
        router.route(
            asset.path,
            get(move || async move {
                let headers = [
                    (header::CONTENT_TYPE, HeaderValue::from_static(asset.content_type)),
                    // Rebuilt binaries serve new files at the same paths.
                    (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
                    (header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff")),
                    (header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CONTENT_SECURITY_POLICY)),
                    (HeaderName::from_static("referrer-policy"), HeaderValue::from_static("no-referrer")),
                ];
                (headers, asset.body).into_response()
            }),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The same-origin paths the page's `src` and `href` attributes name.
    fn linked_paths(html: &str) -> Vec<&str> {
        ["src=\"", "href=\""]
            .iter()
            .flat_map(|attr| html.split(attr).skip(1).filter_map(|rest| rest.split('"').next()))
            .filter(|link| link.starts_with('/') && !link.starts_with("//") && !link.contains('?'))
            .collect()
    }

    #[test]
    fn every_file_the_page_links_is_served_and_every_served_file_is_linked() {
        let page = ASSETS[0];
        assert_eq!(page.path, "/");
        let linked = linked_paths(page.body);
        for asset in &ASSETS[1..] {
            assert!(linked.contains(&asset.path), "the page does not load {}", asset.path);
        }
        for link in linked {
            assert!(ASSETS.iter().any(|a| a.path == link), "the page loads {link}, which is not served");
        }
    }

    #[test]
    fn the_page_has_no_inline_script_or_style_which_the_policy_would_block() {
        let page = ASSETS[0].body;
        for (i, _) in page.match_indices("<script") {
            let tag = &page[i..i + page[i..].find('>').unwrap()];
            assert!(tag.contains("src=\"/"), "inline script: {tag}");
        }
        assert!(!page.contains("<style"), "an inline style sheet");
        // Event-handler and style attributes: ` on<letters>=` and ` style=`.
        for (i, _) in page.match_indices(" on") {
            let name: String = page[i + 3..].chars().take_while(char::is_ascii_lowercase).collect();
            assert!(!page[i + 3 + name.len()..].starts_with('='), "an inline handler: on{name}");
        }
        assert!(!page.contains(" style="), "an inline style attribute");
    }
}
