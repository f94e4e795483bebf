//! The HTTP side of ppm-web: the listening socket (its faults told apart),
//! the client allowlist, and the routes. Read-only: GET (and HEAD) of the
//! page, its script and style, and `/api/state`; any other method is
//! answered 405, any client outside the allowlist 403.

use super::assets::{Asset, ASSETS};
use super::reader::Reader;
use std::io::Cursor;
use std::net::{IpAddr, SocketAddr, TcpListener};
use tiny_http::{Header, Method, Request, Response, Server, StatusCode};

/// Why the listening socket could not be had.
#[derive(Debug, thiserror::Error)]
pub enum BindError {
    /// Another program listens there.
    #[error("cannot listen on {0}: the port is in use (another ppm-web?); stop that program or choose another port with --listen ADDR:PORT")]
    Busy(SocketAddr),
    /// The address is not one of this machine's.
    #[error("cannot listen on {0}: no interface of this machine has that address; use 127.0.0.1 (this machine only), or an address `ip addr` lists")]
    NoSuchAddress(SocketAddr),
    /// A port below 1024 without the privilege for it.
    #[error("cannot listen on {0}: a port below 1024 needs a privilege ppm-web does not have (CAP_NET_BIND_SERVICE); use a port of 1024 or more")]
    NotPermitted(SocketAddr),
    /// Anything else.
    #[error("cannot listen on {0}")]
    Other(SocketAddr, #[source] std::io::Error),
}

/// Binds the listening socket on `addr`.
pub fn bind(addr: SocketAddr) -> Result<TcpListener, BindError> {
    TcpListener::bind(addr).map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => BindError::Busy(addr),
        std::io::ErrorKind::AddrNotAvailable => BindError::NoSuchAddress(addr),
        std::io::ErrorKind::PermissionDenied => BindError::NotPermitted(addr),
        _ => BindError::Other(addr, e),
    })
}

/// Whether `client` is in one of the blocks of `allow` (an IPv4 client
/// seen on an IPv6 socket counts by its IPv4 address).
pub fn allowed(allow: &[ipnet::IpNet], client: IpAddr) -> bool {
    let client = client.to_canonical();
    allow.iter().any(|net| net.contains(&client))
}

/// Whether a request's `Host` header names ppm-web the way a browser on
/// an allowed machine does: an IP address (v4, or v6 in brackets) or
/// `localhost`, with or without a port. Any other name is refused: a page
/// the browser loaded from a domain that later resolves to this address
/// (DNS rebinding) would send that domain's name, and could otherwise read
/// `/api/state` through the allowed browser. No `Host` (HTTP/1.0) is taken.
pub fn host_ok(host: Option<&str>) -> bool {
    let Some(host) = host.map(str::trim) else {
        return true;
    };
    let name = if let Some(rest) = host.strip_prefix('[') {
        match rest.split_once(']') {
            Some((v6, port)) if port.is_empty() || port.starts_with(':') => {
                return v6.parse::<std::net::Ipv6Addr>().is_ok()
            }
            _ => return false,
        }
    } else {
        host.rsplit_once(':').map_or(host, |(n, _)| n)
    };
    name.eq_ignore_ascii_case("localhost") || name.parse::<std::net::Ipv4Addr>().is_ok()
}

/// Serves requests from `server` until it is unblocked, answering with the
/// newest state of `reader`.
pub fn serve(server: &Server, reader: &Reader, allow: &[ipnet::IpNet]) {
    for request in server.incoming_requests() {
        let _ = answer(request, reader, allow);
    }
}

/// The headers every answer carries: nothing cached, nothing framed, no
/// script or style but the page's own.
fn common_headers() -> Vec<Header> {
    [
        ("Cache-Control", "no-store"),
        ("X-Content-Type-Options", "nosniff"),
        ("X-Frame-Options", "DENY"),
        ("Referrer-Policy", "no-referrer"),
        (
            "Content-Security-Policy",
            "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
        ),
    ]
    .iter()
    .filter_map(|(k, v)| Header::from_bytes(k.as_bytes(), v.as_bytes()).ok())
    .collect()
}

fn respond(
    request: Request,
    code: u16,
    content_type: &str,
    body: &[u8],
    extra: &[(&str, &str)],
) -> std::io::Result<()> {
    let mut headers = common_headers();
    headers.extend(
        std::iter::once(("Content-Type", content_type))
            .chain(extra.iter().copied())
            .filter_map(|(k, v)| Header::from_bytes(k.as_bytes(), v.as_bytes()).ok()),
    );
    let head = *request.method() == Method::Head;
    let data = if head { &[][..] } else { body };
    let response = Response::new(
        StatusCode(code),
        headers,
        Cursor::new(data.to_vec()),
        Some(body.len()),
        None,
    );
    request.respond(response)
}

/// Answers one request.
fn answer(request: Request, reader: &Reader, allow: &[ipnet::IpNet]) -> std::io::Result<()> {
    let text = "text/plain; charset=utf-8";
    // tiny_http gives no address only for a client it could not name:
    // refused as well.
    let client_ok = request
        .remote_addr()
        .is_some_and(|a| allowed(allow, a.ip()));
    if !client_ok {
        return respond(
            request,
            403,
            text,
            b"403 forbidden: this address is not in ppm-web's --allow list\n",
            &[],
        );
    }
    let host = request
        .headers()
        .iter()
        .find(|h| h.field.equiv("Host"))
        .map(|h| h.value.as_str().to_string());
    if !host_ok(host.as_deref()) {
        return respond(
            request,
            421,
            text,
            b"421 misdirected request: ask ppm-web by its IP address (http://127.0.0.1:5080/, or the board's address), or as localhost; other host names are refused (a page elsewhere could rename itself to this address)\n",
            &[],
        );
    }
    if !matches!(request.method(), Method::Get | Method::Head) {
        return respond(
            request,
            405,
            text,
            b"405 method not allowed: ppm-web is read-only (GET only)\n",
            &[("Allow", "GET, HEAD")],
        );
    }
    let path = request.url().split('?').next().unwrap_or("/").to_string();
    if path == "/api/state" {
        let state = reader.state();
        return respond(request, 200, "application/json", state.as_bytes(), &[]);
    }
    match ASSETS.iter().find(|a: &&Asset| a.path == path) {
        Some(a) => respond(request, 200, a.content_type, a.body, &[]),
        None => respond(request, 404, text, b"404 not found\n", &[]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_allowlist_takes_blocks_and_mapped_addresses() {
        let allow: Vec<ipnet::IpNet> = ["127.0.0.0/8", "::1/128", "10.1.0.0/16"]
            .iter()
            .map(|s| s.parse().unwrap())
            .collect();
        for (client, ok) in [
            ("127.0.0.1", true),
            ("127.9.9.9", true),
            ("::1", true),
            ("::ffff:127.0.0.1", true),
            ("10.1.200.3", true),
            ("10.2.0.1", false),
            ("192.168.1.5", false),
            ("::ffff:192.168.1.5", false),
        ] {
            assert_eq!(allowed(&allow, client.parse().unwrap()), ok, "{client}");
        }
    }

    #[test]
    fn only_addresses_and_localhost_are_hosts() {
        for (host, ok) in [
            (Some("127.0.0.1:5080"), true),
            (Some("192.168.1.20:5080"), true),
            (Some("192.168.1.20"), true),
            (Some("localhost:5080"), true),
            (Some("LOCALHOST"), true),
            (Some("[::1]:5080"), true),
            (Some("[fd00::21]"), true),
            (None, true),
            (Some("evil.example:5080"), false),
            (Some("raspberrypi.local:5080"), false),
            (Some("127.0.0.1.nip.io"), false),
            (Some("[::1"), false),
            (Some("[::1]x"), false),
            (Some(""), false),
        ] {
            assert_eq!(host_ok(host), ok, "{host:?}");
        }
    }

    #[test]
    fn a_busy_port_is_told_apart() {
        let held = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = held.local_addr().unwrap();
        let e = bind(addr).unwrap_err();
        assert!(matches!(e, BindError::Busy(a) if a == addr), "{e}");
        assert!(e.to_string().contains("in use"), "{e}");
        // TEST-NET-1 (RFC 5737) is on no interface.
        let e = bind("192.0.2.1:8080".parse().unwrap()).unwrap_err();
        assert!(matches!(e, BindError::NoSuchAddress(_)), "{e}");
    }
}
