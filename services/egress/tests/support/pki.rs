//! A throw-away PKI made with the `openssl` command for TLS tests: a CA, a server
//! certificate for 127.0.0.1, clients "viewer" and "intruder", and a second CA nobody
//! trusts with a "rogue-server" certificate. Shared by the egress crate's tests and the
//! workspace's Python-client test.

use egoslam_egress::TlsOptions;
use std::path::PathBuf;
use std::process::Command;

pub struct Pki {
    dir: tempfile::TempDir,
}

impl Pki {
    pub fn new() -> Self {
        let pki = Self {
            dir: tempfile::tempdir().expect("tempdir"),
        };
        pki.authority("ca");
        pki.authority("rogue-ca");
        pki.leaf(
            "server",
            "ca",
            Some("subjectAltName=IP:127.0.0.1,DNS:localhost"),
        );
        pki.leaf("viewer", "ca", None);
        pki.leaf("intruder", "ca", None);
        pki.leaf(
            "rogue-server",
            "rogue-ca",
            Some("subjectAltName=IP:127.0.0.1"),
        );
        pki
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn openssl(&self, args: &[&str]) {
        let out = Command::new("openssl")
            .args(args)
            .current_dir(self.dir.path())
            .output()
            .expect("openssl (deploy/install-deps.sh installs it)");
        assert!(
            out.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }

    fn key(&self, name: &str) {
        let key = format!("{name}.key");
        self.openssl(&[
            "genpkey",
            "-algorithm",
            "EC",
            "-pkeyopt",
            "ec_paramgen_curve:P-256",
            "-out",
            &key,
        ]);
    }

    fn authority(&self, name: &str) {
        self.key(name);
        let (key, pem) = (format!("{name}.key"), format!("{name}.pem"));
        let subject = format!("/CN=egoslam test {name}");
        self.openssl(&[
            "req",
            "-x509",
            "-new",
            "-key",
            &key,
            "-days",
            "2",
            "-subj",
            &subject,
            "-addext",
            "basicConstraints=critical,CA:TRUE",
            "-addext",
            "keyUsage=critical,keyCertSign",
            "-out",
            &pem,
        ]);
    }

    fn leaf(&self, name: &str, ca: &str, alt_names: Option<&str>) {
        self.key(name);
        let (key, csr, pem) = (
            format!("{name}.key"),
            format!("{name}.csr"),
            format!("{name}.pem"),
        );
        let subject = format!("/CN={name}");
        self.openssl(&["req", "-new", "-key", &key, "-subj", &subject, "-out", &csr]);
        let ext = format!("{name}.ext");
        let mut extensions =
            "basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth,clientAuth\n".to_string();
        if let Some(alt) = alt_names {
            extensions += &format!("{alt}\n");
        }
        std::fs::write(self.path(&ext), extensions).expect("ext file");
        let (ca_pem, ca_key) = (format!("{ca}.pem"), format!("{ca}.key"));
        self.openssl(&[
            "x509",
            "-req",
            "-in",
            &csr,
            "-CA",
            &ca_pem,
            "-CAkey",
            &ca_key,
            "-CAcreateserial",
            "-days",
            "2",
            "-extfile",
            &ext,
            "-out",
            &pem,
        ]);
    }

    /// TLS files for `name` (certificate and key), trusting `ca`.
    #[allow(dead_code)] // not every test file that includes this module uses it
    pub fn tls(&self, name: Option<&str>, ca: &str) -> TlsOptions {
        TlsOptions {
            root_ca: Some(self.path(&format!("{ca}.pem"))),
            certificate: name.map(|n| self.path(&format!("{n}.pem"))),
            private_key: name.map(|n| self.path(&format!("{n}.key"))),
            ..Default::default()
        }
    }
}
