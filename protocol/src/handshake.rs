//! The first frames on every connection: who is calling, for what, and proof on both sides
//! that they know the cluster secret, without sending it.
//!
//! ```text
//! caller -> listener  Hello     { version, cluster id, caller nonce, identity, build }
//! listener -> caller  Challenge { version, listener nonce, HMAC(secret, "listener" | id | nc | nl) }
//!                     (or Refused { reason } on a wrong version, cluster id or build)
//! caller -> listener  Proof     { HMAC(secret, "caller" | id | nl | nc) }
//! listener -> caller  Welcome   (or Refused { "wrong cluster secret" })
//! ```
//!
//! Each side checks the other's HMAC in constant time. A peer that fails is told why (when
//! the protocol allows), and both sides return an error that says it.

use std::time::Duration;

use hmac::{Hmac, Mac};
use serde::{Deserialize, Serialize};
use sha2::Sha256;
use tokio::io::{AsyncRead, AsyncWrite};

use crate::{
    PROTOCOL_VERSION, build_id,
    codec::{FrameReader, FrameWriter, ReadError},
    frame::{Frame, NodeId},
    message::{Message, Role},
};

/// Time allowed for the whole handshake.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The shared cluster secret. Its `Debug` never shows it.
#[derive(Clone, PartialEq, Eq)]
pub struct Secret(Vec<u8>);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Secret(<hidden>)")
    }
}

/// A cluster secret too short to be one.
#[derive(Debug, thiserror::Error)]
#[error("the cluster secret must be at least 8 characters")]
pub struct SecretTooShort;

impl Secret {
    pub fn new(text: &str) -> Result<Secret, SecretTooShort> {
        let t = text.trim();
        if t.len() < 8 {
            return Err(SecretTooShort);
        }
        Ok(Secret(t.as_bytes().to_vec()))
    }

    /// A fresh random secret (32 bytes, as 64 hex digits).
    pub fn generate() -> Secret {
        let mut b = [0u8; 32];
        getrandom::fill(&mut b).expect("the operating system's random source");
        Secret(hex(&b).into_bytes())
    }

    /// The text form, to hand to processes this one starts (by environment, never argv).
    pub fn expose(&self) -> String {
        String::from_utf8_lossy(&self.0).into_owned()
    }
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// What a connection is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ConnectionKind {
    /// A node's connection to the host, for registration and lifecycle.
    Control,
    /// A serial link between mesh neighbours.
    Mesh,
    /// A render node's DMA connection to its fork node, or a fork node's G-bus connection.
    Direct,
}

/// Who is calling.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Identity {
    pub role: Role,
    /// The caller's node id, once it has one (not yet when registering).
    pub node: Option<NodeId>,
    pub kind: ConnectionKind,
}

#[derive(Debug, thiserror::Error)]
pub enum HandshakeError {
    #[error("peer refused us: {0}")]
    Refused(String),
    #[error("peer speaks protocol version {theirs}, we speak {ours}")]
    Version { theirs: u32, ours: u32 },
    #[error("peer belongs to cluster {theirs:?}, not {ours:?}")]
    Cluster { theirs: String, ours: String },
    #[error(
        "peer runs build {theirs:?}, this process runs {ours:?}: every process of a cluster must \
         run the same build (rebuild, then restart the nodes with the new binaries)"
    )]
    Build { theirs: String, ours: String },
    #[error("peer does not know the cluster secret")]
    BadSecret,
    #[error("peer sent {0} during the handshake")]
    Unexpected(String),
    #[error("handshake timed out")]
    Timeout,
    #[error("{0}")]
    Read(#[from] ReadError),
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
}

type HmacSha256 = Hmac<Sha256>;

fn mac(secret: &Secret, label: &str, cluster: &str, a: &[u8; 32], b: &[u8; 32]) -> HmacSha256 {
    let mut m = HmacSha256::new_from_slice(&secret.0).expect("HMAC takes keys of any length");
    m.update(label.as_bytes());
    m.update(&(cluster.len() as u32).to_le_bytes());
    m.update(cluster.as_bytes());
    m.update(a);
    m.update(b);
    m
}

fn nonce() -> [u8; 32] {
    let mut n = [0u8; 32];
    getrandom::fill(&mut n).expect("the operating system's random source");
    n
}

async fn next<R: AsyncRead + Unpin>(r: &mut FrameReader<R>) -> Result<Message, HandshakeError> {
    let f = r.read().await?;
    f.message()
        .map_err(|e| HandshakeError::Unexpected(e.to_string()))
}

async fn send<W: AsyncWrite + Unpin>(
    w: &mut FrameWriter<W>,
    m: &Message,
) -> Result<(), HandshakeError> {
    w.write(&Frame::new(0, 0, m, Box::new([]))).await?;
    Ok(())
}

/// The calling side. Returns once the listener has welcomed us.
pub async fn call<R: AsyncRead + Unpin, W: AsyncWrite + Unpin>(
    r: &mut FrameReader<R>,
    w: &mut FrameWriter<W>,
    secret: &Secret,
    cluster: &str,
    identity: Identity,
) -> Result<(), HandshakeError> {
    tokio::time::timeout(HANDSHAKE_TIMEOUT, async {
        let nc = nonce();
        send(
            w,
            &Message::Hello {
                version: PROTOCOL_VERSION,
                cluster_id: cluster.into(),
                nonce: nc,
                identity,
                build: build_id().into(),
            },
        )
        .await?;
        let (nl, proof) = match next(r).await? {
            Message::Challenge {
                version,
                nonce,
                proof,
            } => {
                if version != PROTOCOL_VERSION {
                    return Err(HandshakeError::Version {
                        theirs: version,
                        ours: PROTOCOL_VERSION,
                    });
                }
                (nonce, proof)
            }
            Message::Refused { reason } => return Err(HandshakeError::Refused(reason)),
            other => return Err(HandshakeError::Unexpected(other.name().into())),
        };
        if mac(secret, "listener", cluster, &nc, &nl)
            .verify_slice(&proof)
            .is_err()
        {
            let _ = send(
                w,
                &Message::Refused {
                    reason: "wrong cluster secret".into(),
                },
            )
            .await;
            return Err(HandshakeError::BadSecret);
        }
        let mine: [u8; 32] = mac(secret, "caller", cluster, &nl, &nc)
            .finalize()
            .into_bytes()
            .into();
        send(w, &Message::Proof { proof: mine }).await?;
        match next(r).await? {
            Message::Welcome => Ok(()),
            Message::Refused { reason } => Err(HandshakeError::Refused(reason)),
            other => Err(HandshakeError::Unexpected(other.name().into())),
        }
    })
    .await
    .unwrap_or(Err(HandshakeError::Timeout))
}

/// The listening side. Returns the caller's identity once it has proved itself.
pub async fn answer<R: AsyncRead + Unpin, W: AsyncWrite + Unpin>(
    r: &mut FrameReader<R>,
    w: &mut FrameWriter<W>,
    secret: &Secret,
    cluster: &str,
) -> Result<Identity, HandshakeError> {
    tokio::time::timeout(HANDSHAKE_TIMEOUT, async {
        let (nc, identity) = match next(r).await? {
            Message::Hello { version, cluster_id, nonce, identity, build } => {
                if version != PROTOCOL_VERSION {
                    let reason = format!("protocol version {version} is not supported; this node speaks {PROTOCOL_VERSION}");
                    let _ = send(w, &Message::Refused { reason }).await;
                    return Err(HandshakeError::Version { theirs: version, ours: PROTOCOL_VERSION });
                }
                if cluster_id != cluster {
                    let _ = send(w, &Message::Refused { reason: format!("this is cluster {cluster:?}, not {cluster_id:?}") }).await;
                    return Err(HandshakeError::Cluster { theirs: cluster_id, ours: cluster.into() });
                }
                if build != build_id() {
                    let reason = format!(
                        "this node runs build {:?} and you run {build:?}: every process of a \
                         cluster must run the same build (rebuild, then restart the nodes with the new binaries)",
                        build_id()
                    );
                    let _ = send(w, &Message::Refused { reason }).await;
                    return Err(HandshakeError::Build { theirs: build, ours: build_id().into() });
                }
                (nonce, identity)
            }
            other => return Err(HandshakeError::Unexpected(other.name().into())),
        };
        let nl = nonce();
        let proof: [u8; 32] = mac(secret, "listener", cluster, &nc, &nl).finalize().into_bytes().into();
        send(w, &Message::Challenge { version: PROTOCOL_VERSION, nonce: nl, proof }).await?;
        match next(r).await? {
            Message::Proof { proof } => {
                if mac(secret, "caller", cluster, &nl, &nc).verify_slice(&proof).is_err() {
                    let _ = send(w, &Message::Refused { reason: "wrong cluster secret".into() }).await;
                    return Err(HandshakeError::BadSecret);
                }
            }
            Message::Refused { reason } => return Err(HandshakeError::Refused(reason)),
            other => return Err(HandshakeError::Unexpected(other.name().into())),
        }
        send(w, &Message::Welcome).await?;
        Ok(identity)
    })
    .await
    .unwrap_or(Err(HandshakeError::Timeout))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ident() -> Identity {
        Identity {
            role: Role::Render,
            node: Some(4),
            kind: ConnectionKind::Mesh,
        }
    }

    async fn pair(
        a: &Secret,
        b: &Secret,
        ca: &str,
        cb: &str,
    ) -> (Result<(), HandshakeError>, Result<Identity, HandshakeError>) {
        let (x, y) = tokio::io::duplex(1 << 16);
        let (xr, xw) = tokio::io::split(x);
        let (yr, yw) = tokio::io::split(y);
        let (a, b, ca, cb) = (a.clone(), b.clone(), ca.to_string(), cb.to_string());
        let caller = tokio::spawn(async move {
            call(
                &mut FrameReader::new(xr),
                &mut FrameWriter::new(xw),
                &a,
                &ca,
                ident(),
            )
            .await
        });
        let listener = tokio::spawn(async move {
            answer(
                &mut FrameReader::new(yr),
                &mut FrameWriter::new(yw),
                &b,
                &cb,
            )
            .await
        });
        (caller.await.unwrap(), listener.await.unwrap())
    }

    #[tokio::test]
    async fn same_secret_is_welcome() {
        let s = Secret::new("correct horse battery").unwrap();
        let (c, l) = pair(&s, &s, "magg", "magg").await;
        c.unwrap();
        assert_eq!(l.unwrap(), ident());
    }

    #[tokio::test]
    async fn wrong_secret_is_refused_on_both_sides() {
        let (c, l) = pair(
            &Secret::new("aaaaaaaaaa").unwrap(),
            &Secret::new("bbbbbbbbbb").unwrap(),
            "magg",
            "magg",
        )
        .await;
        assert!(matches!(c, Err(HandshakeError::BadSecret)), "{c:?}");
        assert!(l.is_err());
    }

    #[tokio::test]
    async fn wrong_cluster_is_refused() {
        let s = Secret::new("correct horse battery").unwrap();
        let (c, l) = pair(&s, &s, "one", "two").await;
        assert!(matches!(c, Err(HandshakeError::Refused(_))), "{c:?}");
        assert!(matches!(l, Err(HandshakeError::Cluster { .. })));
    }

    #[tokio::test]
    async fn another_build_is_refused_with_the_reason() {
        let (x, y) = tokio::io::duplex(1 << 16);
        let (xr, xw) = tokio::io::split(x);
        let (yr, yw) = tokio::io::split(y);
        let s = Secret::new("correct horse battery").unwrap();
        let listener = tokio::spawn(async move {
            answer(
                &mut FrameReader::new(yr),
                &mut FrameWriter::new(yw),
                &s,
                "magg",
            )
            .await
        });
        let mut w = FrameWriter::new(xw);
        let mut r = FrameReader::new(xr);
        let other = format!("{} (edited)", build_id());
        send(
            &mut w,
            &Message::Hello {
                version: PROTOCOL_VERSION,
                cluster_id: "magg".into(),
                nonce: [1; 32],
                identity: ident(),
                build: other.clone(),
            },
        )
        .await
        .unwrap();
        match next(&mut r).await.unwrap() {
            Message::Refused { reason } => {
                assert!(reason.contains("same build"), "{reason}");
                assert!(reason.contains(&other), "{reason}");
            }
            m => panic!("expected a refusal, got {m:?}"),
        }
        assert!(matches!(
            listener.await.unwrap(),
            Err(HandshakeError::Build { .. })
        ));
    }

    #[test]
    fn debug_hides_the_secret() {
        let s = Secret::new("hunter2hunter2").unwrap();
        assert!(!format!("{s:?}").contains("hunter2"));
    }
}
