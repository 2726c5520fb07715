//! How an egoslam zenoh session meets the network: endpoints, TLS and access control.
//!
//! Defaults are closed: loopback only, no scouting. Serving other hosts means adding a
//! `tls/` listen endpoint with a certificate (TLS 1.3 via rustls; optionally mutual, so that
//! only clients holding a certificate from the configured CA connect) and keeping
//! [`NetworkOptions::remote_read_only`] on, which installs a zenoh access-control policy
//! (zenoh 1.x `access_control`) under which remote sessions may only *subscribe to* and
//! *query* `egoslam/**`: a `put`, `delete`, queryable or reply arriving from outside is
//! dropped at the session's ingress, so nothing from the network can inject poses, maps or
//! commands, whatever a future version of the pipeline listens to.

use crate::EgressError;
use std::path::{Path, PathBuf};

/// Certificates and keys of a TLS endpoint (PEM files).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TlsOptions {
    /// CA that signed the peer's certificate: a listener uses it to verify client
    /// certificates (mutual TLS), a client to verify the server.
    pub root_ca: Option<PathBuf>,
    /// This side's certificate chain (a listener must have one; a client only for mutual TLS).
    pub certificate: Option<PathBuf>,
    /// The private key of `certificate`.
    pub private_key: Option<PathBuf>,
    /// Listener: require a client certificate signed by `root_ca`.
    pub mutual: bool,
    /// Listener with mutual TLS: only clients whose certificate common name is in this list
    /// receive anything (empty: every client the CA vouches for).
    pub allowed_common_names: Vec<String>,
}

/// Endpoints and security of one session.
#[derive(Debug, Clone, PartialEq)]
pub struct NetworkOptions {
    /// Endpoints to listen on (`tcp/...`, `tls/...`).
    pub listen: Vec<String>,
    /// Routers or peers to connect to.
    pub connect: Vec<String>,
    /// TLS files, needed as soon as an endpoint is `tls/`.
    pub tls: Option<TlsOptions>,
    /// Remote sessions may only subscribe and query (default true; see the module doc).
    pub remote_read_only: bool,
}

impl Default for NetworkOptions {
    fn default() -> Self {
        Self {
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: Vec::new(),
            tls: None,
            remote_read_only: true,
        }
    }
}

impl NetworkOptions {
    /// A client of an egoslam session: connects, listens nowhere, no access control.
    pub fn client(connect: &[String], tls: Option<TlsOptions>) -> Self {
        Self {
            listen: Vec::new(),
            connect: connect.to_vec(),
            tls,
            remote_read_only: false,
        }
    }

    /// The zenoh configuration: peer mode, no scouting, these endpoints, TLS and ACL.
    pub fn zenoh_config(&self) -> Result<zenoh::Config, EgressError> {
        let mut config = zenoh_config(&self.listen, &self.connect)?;
        let uses_tls = self
            .listen
            .iter()
            .chain(&self.connect)
            .any(|e| e.starts_with("tls/"));
        let listens_tls = self.listen.iter().any(|e| e.starts_with("tls/"));
        match (&self.tls, uses_tls) {
            (None, true) => {
                return Err(EgressError::Config(
                    "a tls/ endpoint needs TLS files ([zenoh.tls] in the config)".into(),
                ))
            }
            (Some(tls), _) => apply_tls(&mut config, tls, listens_tls)?,
            (None, false) => {}
        }
        if self.remote_read_only {
            let names = self
                .tls
                .as_ref()
                .map(|t| t.allowed_common_names.as_slice())
                .unwrap_or_default();
            set(&mut config, "access_control", &read_only_acl(names))?;
        }
        for endpoint in &self.listen {
            if endpoint.starts_with("tcp/") && !is_loopback(endpoint) {
                tracing::warn!(
                    endpoint,
                    "listening without TLS on a non-loopback address: anyone on that network can read the results"
                );
            }
        }
        Ok(config)
    }
}

/// The plain zenoh configuration egoslam uses: peer mode, these endpoints, multicast and
/// gossip scouting off (nothing is discovered; clients connect explicitly).
pub fn zenoh_config(listen: &[String], connect: &[String]) -> Result<zenoh::Config, EgressError> {
    let mut config = zenoh::Config::default();
    set(&mut config, "mode", "\"peer\"")?;
    set(&mut config, "listen/endpoints", &json_list(listen))?;
    set(&mut config, "connect/endpoints", &json_list(connect))?;
    set(&mut config, "scouting/multicast/enabled", "false")?;
    set(&mut config, "scouting/gossip/enabled", "false")?;
    Ok(config)
}

fn set(config: &mut zenoh::Config, key: &str, value: &str) -> Result<(), EgressError> {
    config
        .insert_json5(key, value)
        .map_err(|e| EgressError::Config(format!("{key} = {value}: {e}")))
}

fn json_string(s: &str) -> String {
    format!("\"{}\"", s.replace(['"', '\\'], ""))
}

fn json_list<S: AsRef<str>>(v: &[S]) -> String {
    let items: Vec<String> = v.iter().map(|s| json_string(s.as_ref())).collect();
    format!("[{}]", items.join(","))
}

fn is_loopback(endpoint: &str) -> bool {
    let address = endpoint.split_once('/').map_or(endpoint, |(_, a)| a);
    address.starts_with("127.") || address.starts_with("[::1]") || address.starts_with("localhost")
}

/// Checks that a TLS file is there and readable, so that a wrong path is reported by name
/// at start instead of as a failed handshake later.
fn readable(what: &str, path: &Path) -> Result<String, EgressError> {
    std::fs::File::open(path).map_err(|e| EgressError::Tls {
        what: what.into(),
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    Ok(json_string(&path.to_string_lossy()))
}

fn apply_tls(
    config: &mut zenoh::Config,
    tls: &TlsOptions,
    listens: bool,
) -> Result<(), EgressError> {
    let base = "transport/link/tls";
    if let Some(ca) = &tls.root_ca {
        set(
            config,
            &format!("{base}/root_ca_certificate"),
            &readable("root CA", ca)?,
        )?;
    }
    let pair = match (&tls.certificate, &tls.private_key) {
        (Some(c), Some(k)) => Some((readable("certificate", c)?, readable("private key", k)?)),
        (None, None) => None,
        _ => {
            return Err(EgressError::Config(
                "TLS certificate and private_key go together".into(),
            ))
        }
    };
    if tls.mutual && tls.root_ca.is_none() {
        return Err(EgressError::Config(
            "mutual TLS needs root_ca to verify client certificates".into(),
        ));
    }
    if !(tls.allowed_common_names.is_empty() || listens && tls.mutual) {
        return Err(EgressError::Config(
            "allowed_common_names needs a tls/ listen endpoint with mutual = true".into(),
        ));
    }
    if listens {
        let (certificate, key) = pair.ok_or_else(|| {
            EgressError::Config("a tls/ listen endpoint needs certificate and private_key".into())
        })?;
        set(config, &format!("{base}/listen_certificate"), &certificate)?;
        set(config, &format!("{base}/listen_private_key"), &key)?;
        set(
            config,
            &format!("{base}/enable_mtls"),
            &tls.mutual.to_string(),
        )?;
    } else if let Some((certificate, key)) = pair {
        // A client presenting its certificate to a mutual-TLS listener.
        set(config, &format!("{base}/connect_certificate"), &certificate)?;
        set(config, &format!("{base}/connect_private_key"), &key)?;
        set(config, &format!("{base}/enable_mtls"), "true")?;
    }
    Ok(())
}

/// zenoh access control under which remote sessions may only declare subscribers on and
/// query `egoslam/**` (and receive its puts and replies); everything else is denied,
/// including every `put` arriving from outside. With common names, only those clients
/// (authenticated by mutual TLS) are subjects of the policy; any other gets nothing.
fn read_only_acl(common_names: &[String]) -> String {
    let subject = if common_names.is_empty() {
        r#"{ id: "remote" }"#.to_string()
    } else {
        format!(
            r#"{{ id: "remote", cert_common_names: {} }}"#,
            json_list(common_names)
        )
    };
    format!(
        r#"{{
  enabled: true,
  default_permission: "deny",
  rules: [
    {{ id: "results-out", messages: ["put", "delete", "declare_queryable", "reply"],
       flows: ["egress"], permission: "allow", key_exprs: ["egoslam/**"] }},
    {{ id: "clients-in", messages: ["declare_subscriber", "query"],
       flows: ["ingress"], permission: "allow", key_exprs: ["egoslam/**"] }},
  ],
  subjects: [ {subject} ],
  policies: [ {{ id: "read-only", rules: ["results-out", "clients-in"], subjects: ["remote"] }} ],
}}"#
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tls_endpoint_without_files_is_refused_by_name() {
        let options = NetworkOptions {
            listen: vec!["tls/127.0.0.1:7447".into()],
            ..Default::default()
        };
        let e = options.zenoh_config().expect_err("no TLS files");
        assert!(e.to_string().contains("[zenoh.tls]"), "{e}");
    }

    #[test]
    fn a_missing_certificate_file_is_named() {
        let options = NetworkOptions {
            listen: vec!["tls/127.0.0.1:7447".into()],
            tls: Some(TlsOptions {
                certificate: Some("/nonexistent/server.pem".into()),
                private_key: Some("/nonexistent/server.key".into()),
                ..Default::default()
            }),
            ..Default::default()
        };
        let e = options.zenoh_config().expect_err("missing file");
        assert!(e.to_string().contains("/nonexistent/server.pem"), "{e}");
    }

    #[test]
    fn common_names_need_mutual_tls() {
        let options = NetworkOptions {
            tls: Some(TlsOptions {
                allowed_common_names: vec!["viewer".into()],
                ..Default::default()
            }),
            ..Default::default()
        };
        let e = options.zenoh_config().expect_err("no mTLS");
        assert!(e.to_string().contains("mutual"), "{e}");
    }

    #[test]
    fn the_read_only_policy_is_accepted_by_zenoh() {
        // What zenoh holds after parsing: access control on, everything denied but the
        // two rules, and the subject restricted to the given names. (That remote writes
        // are refused and reads served is tests/security.rs's, over real TLS.)
        for names in [vec![], vec!["viewer".to_string(), "ops".to_string()]] {
            let mut config = zenoh::Config::default();
            set(&mut config, "access_control", &read_only_acl(&names)).expect("valid ACL");
            let get = |key: &str| config.get_json(key).expect(key);
            assert_eq!(get("access_control/enabled"), "true");
            assert_eq!(get("access_control/default_permission"), "\"deny\"");
            let rules: serde_json::Value =
                serde_json::from_str(&get("access_control/rules")).expect("rules");
            let rules = rules.as_array().expect("a list");
            assert_eq!(rules.len(), 2);
            for rule in rules {
                let has = |field: &str, value: &str| {
                    rule[field]
                        .as_array()
                        .expect(field)
                        .iter()
                        .any(|v| v == value)
                };
                // Nothing from outside may write: no put or delete flows in.
                if has("flows", "ingress") {
                    assert!(
                        !has("messages", "put") && !has("messages", "delete"),
                        "{rule}"
                    );
                }
                assert_eq!(
                    rule["key_exprs"],
                    serde_json::json!(["egoslam/**"]),
                    "{rule}"
                );
            }
            let subjects: serde_json::Value =
                serde_json::from_str(&get("access_control/subjects")).expect("subjects");
            let expected = if names.is_empty() {
                serde_json::Value::Null
            } else {
                serde_json::json!(names)
            };
            assert_eq!(subjects[0]["cert_common_names"], expected);
        }
    }

    #[test]
    fn loopback_endpoints_are_recognised() {
        assert!(is_loopback("tcp/127.0.0.1:7447"));
        assert!(is_loopback("tcp/[::1]:7447"));
        assert!(!is_loopback("tcp/0.0.0.0:7447"));
        assert!(!is_loopback("tcp/192.168.1.4:7447"));
    }
}
