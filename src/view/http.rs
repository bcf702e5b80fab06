//! The viewer's HTTP/1.1 server: hyper's HTTP/1 connections on a current-thread tokio runtime,
//! one request per connection (`Connection: close`). Handlers are plain functions from a
//! [`Request`] to a [`Response`] ([`serve`]); they run on a small pool of threads.
//!
//! What a client can hold, and for how long:
//! * a connection is a task of a few KiB, at most [`MAX_CONNECTIONS`] at once (more are
//!   answered `503` with `Retry-After` and closed);
//! * its request head (request line + headers, at most [`MAX_HEAD`] bytes and [`MAX_HEADERS`]
//!   headers: `431`; not HTTP: `400`) must be complete within [`HEAD_DEADLINE`] of the
//!   connection's start — a deadline, not an idle timeout, so trickling bytes does not extend it
//!   (`408`, and the connection is closed);
//! * only a complete request takes one of the [`MAX_HANDLERS`] handler slots; it waits at most
//!   [`QUEUE_WAIT`] for one (then `503` with `Retry-After`), and its response must be sent within
//!   [`RESPONSE_DEADLINE`];
//! * bodies are never read (the API is `GET` only); after the response what the client still
//!   sends is drained for a moment, at most [`DRAIN`] bytes, so that closing does not reset the
//!   connection before the client has read its answer.
use std::io;
use std::net::TcpListener;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use hyper::body::{Frame, SizeHint};
use hyper::header::{self, HeaderValue};
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::sync::Semaphore;

/// The longest request head (request line + headers) accepted: 16 KiB.
pub const MAX_HEAD: usize = 16 * 1024;
/// The most headers accepted.
pub const MAX_HEADERS: usize = 64;
/// The time from a connection's start by which its request head must be complete.
pub const HEAD_DEADLINE: Duration = Duration::from_secs(5);
/// Connections open at once; more are answered `503` at once.
pub const MAX_CONNECTIONS: usize = 512;
/// Requests handled at once (threads running handlers).
pub const MAX_HANDLERS: usize = 16;
/// How long a complete request waits for a handler slot before it is answered `503`.
pub const QUEUE_WAIT: Duration = Duration::from_secs(10);
/// The time from a complete request head by which its response must have been sent.
pub const RESPONSE_DEADLINE: Duration = Duration::from_secs(300);
/// The seconds a `503` asks the client to wait (`Retry-After`).
pub const RETRY_AFTER_S: u32 = 1;
/// The most bytes drained from a client after its response, for at most half a second.
pub const DRAIN: u64 = 4 << 20;

/// A parsed request: method, the target's path (still percent-encoded) and query, the Host header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    pub method: String,
    pub path: String,
    pub query: String,
    pub host: Option<String>,
}

/// A response to write.
#[derive(Debug, Clone)]
pub struct Response {
    pub status: u16,
    pub content_type: &'static str,
    pub body: Body,
}

/// A response body: bytes in memory, shared bytes, bytes embedded in the binary, or a file
/// streamed from disk.
#[derive(Debug, Clone)]
pub enum Body {
    Bytes(Vec<u8>),
    Static(&'static [u8]),
    Shared(Arc<Vec<u8>>),
    File(std::path::PathBuf, u64),
}

impl Response {
    /// A plain-text response (errors: one line).
    pub fn text(status: u16, text: impl Into<String>) -> Response {
        let mut t = text.into();
        t.push('\n');
        Response {
            status,
            content_type: "text/plain; charset=utf-8",
            body: Body::Bytes(t.into_bytes()),
        }
    }

    /// A JSON response.
    pub fn json(status: u16, value: &serde_json::Value) -> Response {
        Response {
            status,
            content_type: "application/json",
            body: Body::Bytes(value.to_string().into_bytes()),
        }
    }

    /// A JSON error `{"error": message}`.
    pub fn error(status: u16, message: impl Into<String>) -> Response {
        Response::json(status, &serde_json::json!({ "error": message.into() }))
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "Status",
    }
}

/// The body of a response as hyper sends it: bytes in memory, or a file read in chunks.
enum Payload {
    Full(Option<Bytes>),
    File { file: tokio::fs::File, left: u64 },
}

/// A shared buffer as the bytes of a body (without copying it).
struct SharedBytes(Arc<Vec<u8>>);

impl AsRef<[u8]> for SharedBytes {
    fn as_ref(&self) -> &[u8] {
        &self.0
    }
}

/// Bytes of a file body read per frame.
const FILE_CHUNK: u64 = 256 * 1024;

impl hyper::body::Body for Payload {
    type Data = Bytes;
    type Error = io::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, io::Error>>> {
        match self.get_mut() {
            Payload::Full(b) => Poll::Ready(b.take().map(|b| Ok(Frame::data(b)))),
            Payload::File { file, left } => {
                if *left == 0 {
                    return Poll::Ready(None);
                }
                let mut buf = vec![0u8; (*left).min(FILE_CHUNK) as usize];
                let mut rb = tokio::io::ReadBuf::new(&mut buf);
                match tokio::io::AsyncRead::poll_read(Pin::new(file), cx, &mut rb) {
                    Poll::Pending => Poll::Pending,
                    Poll::Ready(Err(e)) => Poll::Ready(Some(Err(e))),
                    Poll::Ready(Ok(())) => {
                        let n = rb.filled().len();
                        if n == 0 {
                            return Poll::Ready(Some(Err(io::Error::new(
                                io::ErrorKind::UnexpectedEof,
                                "the file became shorter while it was sent",
                            ))));
                        }
                        buf.truncate(n);
                        *left -= n as u64;
                        Poll::Ready(Some(Ok(Frame::data(Bytes::from(buf)))))
                    }
                }
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        match self {
            Payload::Full(b) => b.is_none(),
            Payload::File { left, .. } => *left == 0,
        }
    }

    fn size_hint(&self) -> SizeHint {
        match self {
            Payload::Full(b) => SizeHint::with_exact(b.as_ref().map_or(0, |b| b.len() as u64)),
            Payload::File { left, .. } => SizeHint::with_exact(*left),
        }
    }
}

/// `resp` as hyper sends it (without its body for `HEAD`).
async fn to_hyper(resp: Response, head_only: bool) -> hyper::Response<Payload> {
    let len = match &resp.body {
        Body::Bytes(b) => b.len() as u64,
        Body::Static(b) => b.len() as u64,
        Body::Shared(b) => b.len() as u64,
        Body::File(_, n) => *n,
    };
    let status = resp.status;
    let payload = if head_only {
        Payload::Full(None)
    } else {
        match resp.body {
            Body::Bytes(b) => Payload::Full(Some(Bytes::from(b))),
            Body::Static(b) => Payload::Full(Some(Bytes::from_static(b))),
            Body::Shared(b) => Payload::Full(Some(Bytes::from_owner(SharedBytes(b)))),
            Body::File(p, n) => match tokio::fs::File::open(&p).await {
                Ok(file) => Payload::File { file, left: n },
                Err(e) => {
                    return Box::pin(to_hyper(
                        Response::text(404, format!("{}: {e}", p.display())),
                        head_only,
                    ))
                    .await;
                }
            },
        }
    };
    let mut r = hyper::Response::new(payload);
    *r.status_mut() =
        hyper::StatusCode::from_u16(status).unwrap_or(hyper::StatusCode::INTERNAL_SERVER_ERROR);
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(resp.content_type),
    );
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    h.insert(header::CONNECTION, HeaderValue::from_static("close"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    if status == 503 {
        h.insert(header::RETRY_AFTER, HeaderValue::from(RETRY_AFTER_S));
    }
    r
}

/// The head of a plain-text response written straight to a socket (the answers given without
/// hyper: `408` after the head deadline, `503` beyond [`MAX_CONNECTIONS`]).
fn raw_response(status: u16, text: &str) -> Vec<u8> {
    let retry = if status == 503 {
        format!("Retry-After: {RETRY_AFTER_S}\r\n")
    } else {
        String::new()
    };
    format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\nCache-Control: no-store\r\n{retry}\r\n{text}\n",
        reason(status),
        text.len() + 1
    )
    .into_bytes()
}

type Handler = dyn Fn(&Request) -> Response + Send + Sync;

/// Serves `listener` until the process ends: each request answered by `handle`, on one of
/// [`MAX_HANDLERS`] threads. Returns only when the server cannot start.
pub fn serve<H>(listener: TcpListener, handle: H) -> io::Result<()>
where
    H: Fn(&Request) -> Response + Send + Sync + 'static,
{
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_io()
        .enable_time()
        .max_blocking_threads(MAX_HANDLERS + 8)
        .thread_name("gs4city-view")
        .build()?;
    listener.set_nonblocking(true)?;
    let handle: Arc<Handler> = Arc::new(handle);
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::from_std(listener)?;
        let connections = Arc::new(Semaphore::new(MAX_CONNECTIONS));
        let refusals = Arc::new(Semaphore::new(64));
        let handlers = Arc::new(Semaphore::new(MAX_HANDLERS));
        loop {
            let stream = match listener.accept().await {
                Ok((s, _)) => s,
                Err(e) => {
                    // Out of file descriptors, or a connection reset before it was taken.
                    log::debug!("view: accept: {e}");
                    tokio::time::sleep(Duration::from_millis(10)).await;
                    continue;
                }
            };
            if let Ok(slot) = Arc::clone(&connections).try_acquire_owned() {
                let (handle, handlers) = (Arc::clone(&handle), Arc::clone(&handlers));
                tokio::spawn(async move {
                    connection(stream, handle, handlers).await;
                    drop(slot);
                });
            } else if let Ok(slot) = Arc::clone(&refusals).try_acquire_owned() {
                tokio::spawn(async move {
                    let msg = raw_response(503, "too many connections; try again");
                    let _ = tokio::time::timeout(Duration::from_secs(1), async {
                        let _ = write_all(&stream, &msg).await;
                    })
                    .await;
                    drain(stream).await;
                    drop(slot);
                });
            }
            // Beyond both: the connection is closed unanswered.
        }
    })
}

/// Writes `bytes` to `stream`.
async fn write_all(stream: &tokio::net::TcpStream, mut bytes: &[u8]) -> io::Result<()> {
    while !bytes.is_empty() {
        stream.writable().await?;
        match stream.try_write(bytes) {
            Ok(n) => bytes = &bytes[n..],
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Closes our side of `stream`, then reads and drops what the client still sends (at most
/// [`DRAIN`] bytes, for at most half a second), so that the close is not a reset that could
/// discard the response before the client read it.
async fn drain(stream: tokio::net::TcpStream) {
    let Ok(std) = stream.into_std() else { return };
    let _ = std.shutdown(std::net::Shutdown::Write);
    let Ok(stream) = tokio::net::TcpStream::from_std(std) else {
        return;
    };
    let _ = tokio::time::timeout(Duration::from_millis(500), async {
        let mut left = DRAIN;
        let mut buf = vec![0u8; 16 * 1024];
        while left > 0 {
            if stream.readable().await.is_err() {
                return;
            }
            match stream.try_read(&mut buf) {
                Ok(0) => return,
                Ok(n) => left = left.saturating_sub(n as u64),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(_) => return,
            }
        }
    })
    .await;
}

/// One connection: hyper reads the head and writes the response; the head must be complete by
/// [`HEAD_DEADLINE`] (else `408`), the response sent by [`RESPONSE_DEADLINE`] after it.
async fn connection(stream: tokio::net::TcpStream, handle: Arc<Handler>, handlers: Arc<Semaphore>) {
    // A second handle on the socket, to answer 408 and to drain after hyper let go of it.
    let Ok(std) = stream.into_std() else { return };
    let Ok(keep) = std.try_clone() else { return };
    let Ok(stream) = tokio::net::TcpStream::from_std(std) else {
        return;
    };
    let (head_tx, head_rx) = tokio::sync::oneshot::channel::<()>();
    let head_tx = Mutex::new(Some(head_tx));
    let service = hyper::service::service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
        if let Some(tx) = head_tx.lock().unwrap_or_else(|e| e.into_inner()).take() {
            let _ = tx.send(());
        }
        let (handle, handlers) = (Arc::clone(&handle), Arc::clone(&handlers));
        async move { Ok::<_, std::convert::Infallible>(respond(req, handle, handlers).await) }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .keep_alive(false)
        .max_buf_size(MAX_HEAD)
        .max_header_size(MAX_HEAD)
        .max_headers(MAX_HEADERS)
        // A backstop: the deadline below answers 408 first.
        .header_read_timeout(HEAD_DEADLINE + Duration::from_secs(1));
    let conn = builder.serve_connection(TokioIo::new(stream), service);
    let mut task = tokio::spawn(conn);
    let timed_out = match tokio::time::timeout(HEAD_DEADLINE, head_rx).await {
        // A complete head: its response goes out within its deadline.
        Ok(Ok(())) => {
            if tokio::time::timeout(RESPONSE_DEADLINE, &mut task)
                .await
                .is_err()
            {
                task.abort();
            }
            false
        }
        // The connection ended without a request (closed; or a bad head hyper answered).
        Ok(Err(_)) => {
            let _ = (&mut task).await;
            false
        }
        Err(_) => {
            task.abort();
            let _ = (&mut task).await;
            true
        }
    };
    let Ok(keep) = tokio::net::TcpStream::from_std(keep) else {
        return;
    };
    if timed_out {
        let msg = raw_response(408, "the request head did not arrive in time");
        let _ = tokio::time::timeout(Duration::from_secs(1), write_all(&keep, &msg)).await;
    }
    drain(keep).await;
}

/// Answers one request: waits for a handler slot (at most [`QUEUE_WAIT`]; then `503`) and runs
/// the handler on the blocking pool.
async fn respond(
    req: hyper::Request<hyper::body::Incoming>,
    handle: Arc<Handler>,
    handlers: Arc<Semaphore>,
) -> hyper::Response<Payload> {
    let r = Request {
        method: req.method().as_str().to_string(),
        path: req.uri().path().to_string(),
        query: req.uri().query().unwrap_or("").to_string(),
        host: req
            .headers()
            .get(header::HOST)
            .map(|h| String::from_utf8_lossy(h.as_bytes()).into_owned()),
    };
    let head_only = r.method == "HEAD";
    let slot = match tokio::time::timeout(QUEUE_WAIT, handlers.acquire_owned()).await {
        Ok(Ok(slot)) => slot,
        _ => {
            return to_hyper(
                Response::text(503, "the server is busy; try again"),
                head_only,
            )
            .await;
        }
    };
    let answer = tokio::task::spawn_blocking(move || {
        let resp = handle(&r);
        drop(slot);
        resp
    })
    .await
    .unwrap_or_else(|_| Response::text(500, "the handler failed"));
    to_hyper(answer, head_only).await
}
