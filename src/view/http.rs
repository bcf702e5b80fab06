//! The viewer's HTTP/1.1 transport on `std::net`, one request per connection (`Connection:
//! close`): the request head is read up to [`MAX_HEAD`] bytes and parsed by `httparse`; a head
//! that is too long, has too many headers, is not HTTP, or does not arrive within
//! [`READ_TIMEOUT`] gets its status code and the connection is closed, so no client can hold
//! the server's memory or all of its threads. Bodies are never read (the API is `GET` only).
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

/// The longest request head (request line + headers) accepted: 16 KiB.
pub const MAX_HEAD: usize = 16 * 1024;
/// The most headers accepted.
pub const MAX_HEADERS: usize = 64;
/// How long a client may take to send its request head, and to take a response.
pub const READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Connections served at once; more are answered `503` at once.
pub const MAX_CONNECTIONS: usize = 32;

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

/// Why a request head could not be read; each is answered with its status and the connection closed.
#[derive(Debug)]
pub enum HeadError {
    /// The client closed the connection (or it failed) before a head arrived: nothing to answer.
    Closed,
    /// The head did not arrive in time.
    Timeout,
    /// Longer than [`MAX_HEAD`] or more than [`MAX_HEADERS`] headers.
    TooLarge(String),
    /// Not an HTTP/1.x request head.
    Malformed(String),
}

/// Reads and parses one request head from `stream`.
pub fn read_head(stream: &mut impl Read) -> Result<Request, HeadError> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 2048];
    loop {
        let n = match stream.read(&mut chunk) {
            Ok(0) => {
                return Err(if buf.is_empty() {
                    HeadError::Closed
                } else {
                    HeadError::Malformed("the connection ended inside the request head".into())
                });
            }
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                return Err(HeadError::Timeout);
            }
            Err(_) => return Err(HeadError::Closed),
        };
        buf.extend_from_slice(&chunk[..n]);
        let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
        let mut req = httparse::Request::new(&mut headers);
        match req.parse(&buf) {
            Ok(httparse::Status::Complete(_)) => {
                let target = req.path.unwrap_or("/");
                let (path, query) = target.split_once('?').unwrap_or((target, ""));
                let host = req
                    .headers
                    .iter()
                    .find(|h| h.name.eq_ignore_ascii_case("host"))
                    .map(|h| String::from_utf8_lossy(h.value).into_owned());
                return Ok(Request {
                    method: req.method.unwrap_or("").to_string(),
                    path: path.to_string(),
                    query: query.to_string(),
                    host,
                });
            }
            Ok(httparse::Status::Partial) => {
                if buf.len() > MAX_HEAD {
                    return Err(HeadError::TooLarge(format!(
                        "the request head is longer than {MAX_HEAD} bytes"
                    )));
                }
            }
            Err(httparse::Error::TooManyHeaders) => {
                return Err(HeadError::TooLarge(format!(
                    "more than {MAX_HEADERS} request headers"
                )));
            }
            Err(e) => return Err(HeadError::Malformed(format!("not an HTTP request: {e}"))),
        }
        if buf.len() > MAX_HEAD {
            return Err(HeadError::TooLarge(format!(
                "the request head is longer than {MAX_HEAD} bytes"
            )));
        }
    }
}

/// Writes `resp` (without its body for `HEAD`).
pub fn write_response(stream: &mut impl Write, resp: &Response, head_only: bool) -> io::Result<()> {
    let len = match &resp.body {
        Body::Bytes(b) => b.len() as u64,
        Body::Static(b) => b.len() as u64,
        Body::Shared(b) => b.len() as u64,
        Body::File(_, n) => *n,
    };
    let head = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {len}\r\nConnection: close\r\nCache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\n\r\n",
        resp.status,
        reason(resp.status),
        resp.content_type
    );
    stream.write_all(head.as_bytes())?;
    if !head_only {
        match &resp.body {
            Body::Bytes(b) => stream.write_all(b)?,
            Body::Static(b) => stream.write_all(b)?,
            Body::Shared(b) => stream.write_all(b)?,
            Body::File(p, n) => {
                let f = std::fs::File::open(p)?;
                io::copy(&mut f.take(*n), stream)?;
            }
        }
    }
    stream.flush()
}

/// Serves `listener` forever: each connection on its own thread (at most [`MAX_CONNECTIONS`]),
/// its request answered by `handle`.
pub fn serve<H>(listener: TcpListener, handle: H)
where
    H: Fn(&Request) -> Response + Send + Sync + 'static,
{
    let handle = Arc::new(handle);
    let active = Arc::new(AtomicUsize::new(0));
    for conn in listener.incoming() {
        let Ok(mut stream) = conn else { continue };
        if active.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
            active.fetch_sub(1, Ordering::SeqCst);
            let _ = stream.set_write_timeout(Some(READ_TIMEOUT));
            let _ = write_response(
                &mut stream,
                &Response::text(503, "too many connections; try again"),
                false,
            );
            continue;
        }
        let (handle, slot) = (Arc::clone(&handle), Arc::clone(&active));
        let spawned = std::thread::Builder::new()
            .name("gs4city-view".into())
            .spawn(move || {
                connection(&mut stream, &*handle);
                slot.fetch_sub(1, Ordering::SeqCst);
            });
        if spawned.is_err() {
            // The closure (and its stream) is gone: the slot is given back.
            active.fetch_sub(1, Ordering::SeqCst);
            log::warn!("view: could not start a connection thread");
        }
    }
}

fn connection(stream: &mut TcpStream, handle: &(dyn Fn(&Request) -> Response + Send + Sync)) {
    let _ = stream.set_read_timeout(Some(READ_TIMEOUT));
    let _ = stream.set_write_timeout(Some(READ_TIMEOUT));
    let peer: Option<SocketAddr> = stream.peer_addr().ok();
    let (resp, head_only) = match read_head(stream) {
        Ok(req) => {
            let head_only = req.method == "HEAD";
            (handle(&req), head_only)
        }
        Err(HeadError::Closed) => return,
        Err(HeadError::Timeout) => (
            Response::text(408, "the request head did not arrive in time"),
            false,
        ),
        Err(HeadError::TooLarge(m)) => (Response::text(431, m), false),
        Err(HeadError::Malformed(m)) => (Response::text(400, m), false),
    };
    if let Err(e) = write_response(stream, &resp, head_only) {
        log::debug!("view: writing to {peer:?}: {e}");
    }
    // Close our side, then drain what the client still sends (a body, the rest of a long
    // head) for a moment, so that closing does not reset the connection before the client
    // has read the response.
    let _ = stream.shutdown(std::net::Shutdown::Write);
    let _ = stream.set_read_timeout(Some(Duration::from_millis(500)));
    let _ = io::copy(&mut stream.take(DRAIN), &mut io::sink());
}

/// The most bytes drained from a client after its response.
const DRAIN: u64 = 4 << 20;
