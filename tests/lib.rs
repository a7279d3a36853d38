//! Cross-crate tests live in `tests/tests/`. This library holds what tests of several crates
//! share: finding a tool they need (failing, never skipping, when it is missing) and real
//! components they start on loopback (nginx).

use std::path::{Path, PathBuf};

/// `tool`'s path (searched in ~/.cargo/bin, PATH, /usr/sbin); panics naming `hint` when it is
/// missing: a test that needs it fails rather than skip.
pub fn need(tool: &str, hint: &str) -> PathBuf {
    let home = std::env::var("HOME").unwrap_or_default();
    let path = std::env::var("PATH").unwrap_or_default();
    for dir in std::iter::once(format!("{home}/.cargo/bin"))
        .chain(path.split(':').map(String::from))
        .chain(["/usr/sbin".to_string(), "/sbin".to_string()])
    {
        let p = Path::new(&dir).join(tool);
        if p.is_file() {
            return p;
        }
    }
    panic!("{tool} is not installed ({hint}): this test needs it and does not skip");
}

/// A free loopback port (bound and released: another process may take it first, rarely).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Debian's nginx on a free loopback port with `server` as its server block's body (beside
/// `listen`) and `http` before it, from a temporary prefix; stopped when dropped.
pub struct Nginx {
    child: std::process::Child,
    pub port: u16,
    _dir: tempfile::TempDir,
}

impl Nginx {
    pub fn start(server: &str) -> Nginx {
        Self::start_with("", server)
    }

    pub fn start_with(http: &str, server: &str) -> Nginx {
        let nginx = need("nginx", "scripts/setup installs Debian's nginx-light");
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let d = dir.path().display();
        let conf = format!(
            "daemon off; user root; worker_processes 1; pid {d}/nginx.pid; error_log {d}/error.log;\n\
             events {{}}\n\
             http {{ access_log off; client_body_temp_path {d}/b; proxy_temp_path {d}/p;\n\
               fastcgi_temp_path {d}/f; uwsgi_temp_path {d}/u; scgi_temp_path {d}/s;\n\
               {http}\n\
               server {{ listen 127.0.0.1:{port}; {server} }} }}\n"
        );
        std::fs::write(dir.path().join("nginx.conf"), conf).unwrap();
        let child = std::process::Command::new(nginx)
            .arg("-p")
            .arg(dir.path())
            .arg("-c")
            .arg(dir.path().join("nginx.conf"))
            .stdout(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                t0.elapsed() < std::time::Duration::from_secs(20),
                "nginx did not listen"
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        Nginx {
            child,
            port,
            _dir: dir,
        }
    }
}

impl Drop for Nginx {
    /// SIGTERM, nginx's fast shutdown: the master stops its workers before it exits (a killed
    /// master leaves its workers running).
    fn drop(&mut self) {
        let pid = self.child.id().to_string();
        let asked = std::process::Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .is_ok_and(|s| s.success());
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while asked && std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
