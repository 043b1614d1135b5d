//! Servers that lie or stall, on loopback (plain TCP, so that the answers can be as wrong as a
//! broken proxy's): the reader takes no more than it asked, and gives up on silence. A 200
//! with a whole 100 GB file, or a 206 with a huge body, passed 6 GB into memory before.

use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

/// How a server answers a range read (the length probe, `bytes=0-0`, is always answered
/// right, with a file of `LENGTH` bytes, unless the scenario is about it).
#[derive(Clone, Copy)]
enum Lie {
    /// Ignores ranges: a 200 with a file of 100 GB (said in Content-Length).
    WholeSaid,
    /// Ignores ranges: a 200 whose body runs on with no length said.
    WholeUnsaid,
    /// A 206 whose body is far longer than the range asked.
    LongRange,
    /// A 206 that sends half the range, then nothing.
    Stall,
}

const LENGTH: u64 = 5000;

/// Serves `lie` on a loopback port until the test ends: one answer a connection, each saying
/// `Connection: close` (a client that reused the closed connection of the length probe failed
/// "sending the request" instead of meeting the lie).
fn serve(lie: Lie) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for conn in listener.incoming().flatten() {
            std::thread::spawn(move || answer(conn, lie));
        }
    });
    format!("http://127.0.0.1:{port}/asset.fra")
}

fn answer(mut conn: TcpStream, lie: Lie) {
    let mut range = String::new();
    let mut reader = BufReader::new(conn.try_clone().unwrap());
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap_or(0) == 0 {
            return;
        }
        if line.to_ascii_lowercase().starts_with("range:") {
            range = line[6..].trim().to_string();
        }
        if line == "\r\n" {
            break;
        }
    }
    let zeros = vec![0u8; 1 << 16];
    let probe = range == "bytes=0-0";
    let _ = match (lie, probe) {
        (Lie::WholeSaid, _) => {
            let _ = conn.write_all(b"HTTP/1.1 200 OK\r\nContent-Length: 107374182400\r\n\r\n");
            // As long as the reader reads.
            while conn.write_all(&zeros).is_ok() {}
            Ok(())
        }
        (Lie::WholeUnsaid, _) => {
            let _ = conn.write_all(b"HTTP/1.1 200 OK\r\nConnection: close\r\n\r\n");
            while conn.write_all(&zeros).is_ok() {}
            Ok(())
        }
        (_, true) => conn.write_all(
            format!("HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 0-0/{LENGTH}\r\nContent-Length: 1\r\nConnection: close\r\n\r\nF").as_bytes(),
        ),
        (Lie::LongRange, false) => {
            let _ = conn.write_all(
                format!("HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 0-99/{LENGTH}\r\nConnection: close\r\n\r\n").as_bytes(),
            );
            while conn.write_all(&zeros).is_ok() {}
            Ok(())
        }
        (Lie::Stall, false) => {
            let _ = conn.write_all(
                format!("HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 0-99/{LENGTH}\r\nContent-Length: 100\r\nConnection: close\r\n\r\n").as_bytes(),
            );
            let _ = conn.write_all(&zeros[..50]);
            std::thread::sleep(Duration::from_secs(30));
            Ok(())
        }
    };
}

#[test]
fn a_server_that_ignores_ranges_sends_no_more_than_a_small_file() {
    for lie in [Lie::WholeSaid, Lie::WholeUnsaid] {
        let t = Instant::now();
        let err = match fractile_remote::open(&serve(lie)) {
            Ok(_) => panic!("a 100 GB answer was taken"),
            Err(e) => e,
        };
        assert!(err.to_string().contains("ignores Range"), "{err}");
        // Refused from its length, or after the most a whole answer may carry (256 MiB over
        // loopback), not after the whole body.
        assert!(t.elapsed() < Duration::from_secs(20), "{:?}", t.elapsed());
    }
}

#[test]
fn a_range_answer_longer_than_asked_is_refused() {
    let source = fractile_remote::open(&serve(Lie::LongRange)).expect("the length probe");
    assert_eq!(source.len(), LENGTH);
    let t = Instant::now();
    let err = source
        .read(0, 100)
        .expect_err("a body longer than the range");
    assert!(err.to_string().contains("at most were asked"), "{err}");
    assert!(t.elapsed() < Duration::from_secs(10));
}

#[test]
fn a_server_that_stalls_mid_body_times_out() {
    let source = fractile_remote::open_with(&serve(Lie::Stall), Duration::from_secs(1))
        .expect("the length probe");
    let t = Instant::now();
    let err = source.read(0, 100).expect_err("a stalled body");
    assert_eq!(err.kind(), std::io::ErrorKind::TimedOut, "{err}");
    assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
}
