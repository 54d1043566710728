//! Request bodies an error answers before reading them are read to their end (up to a bound)
//! before the answer is sent.
//!
//! Why: a 413 (or any early error) sent while the client is still sending its body, followed
//! by closing the connection with the body's bytes unread, makes the kernel reset the
//! connection, and most HTTP clients then report "connection reset" instead of the problem
//! the server sent. Reading what is left first lets the client finish sending and read the
//! answer. Bodies far beyond any limit are not read: past [`DRAIN_MAX_BYTES`] or
//! [`DRAIN_TIMEOUT`] the connection is closed (`Connection: close`) as before.

use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::Request;
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::Response;
use http_body_util::BodyExt;
use tokio::sync::Mutex;

/// At most this many unread body bytes are read and dropped after an error answer.
pub const DRAIN_MAX_BYTES: u64 = 256 << 20;

/// Reading an unread body after an error answer stops after this long.
pub const DRAIN_TIMEOUT: Duration = Duration::from_secs(30);

/// Middleware (outside the body limit): the body the handler (or the limit) left unread is
/// read and dropped before an error response goes out.
pub async fn drain_unread_body(request: Request, next: Next) -> Response {
    if !has_body(&request) {
        return next.run(request).await;
    }
    let (parts, body) = request.into_parts();
    // The handler reads the body through the shared slot; what it leaves stays there.
    let slot = Arc::new(Mutex::new(Some(body)));
    let reader = futures_util::stream::unfold(slot.clone(), |slot| async move {
        let next = {
            let mut guard = slot.lock().await;
            let body = guard.as_mut()?;
            loop {
                match body.frame().await {
                    None => {
                        *guard = None;
                        break None;
                    }
                    Some(Ok(frame)) => {
                        if let Ok(data) = frame.into_data() {
                            break Some(Ok(data));
                        }
                    }
                    Some(Err(e)) => break Some(Err(e)),
                }
            }
        };
        next.map(|item| (item, slot))
    });
    let mut response = next.run(Request::from_parts(parts, Body::from_stream(reader))).await;
    if !(response.status().is_client_error() || response.status().is_server_error()) {
        return response;
    }
    // Still locked: something still reads the body (it outlived the handler); leave it.
    let Ok(mut guard) = slot.try_lock() else { return response };
    if let Some(body) = guard.take() {
        let read_all = tokio::time::timeout(DRAIN_TIMEOUT, drain(body, DRAIN_MAX_BYTES)).await.unwrap_or(false);
        if !read_all {
            response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
    }
    response
}

/// Whether the request declares a body (a non-zero length, or a chunked one).
fn has_body(request: &Request) -> bool {
    let headers = request.headers();
    let length = headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
    length.is_some_and(|n| n > 0) || headers.contains_key(header::TRANSFER_ENCODING)
}

/// Reads and drops `body` to its end; false when it holds more than `max_bytes` or fails.
async fn drain(mut body: Body, max_bytes: u64) -> bool {
    let mut read = 0u64;
    loop {
        match body.frame().await {
            None => return true,
            Some(Ok(frame)) => {
                read += frame.data_ref().map_or(0, |d| d.len() as u64);
                if read > max_bytes {
                    return false;
                }
            }
            Some(Err(_)) => return false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_body_is_drained_to_its_end_within_the_bound_and_not_beyond() {
        let body = || Body::from(vec![7u8; 10_000]);
        assert!(drain(body(), 10_000).await);
        assert!(!drain(body(), 9_999).await);
        let failing =
            Body::from_stream(futures_util::stream::iter([Err::<Vec<u8>, _>(std::io::Error::other("cut off"))]));
        assert!(!drain(failing, 10_000).await);
    }
}
