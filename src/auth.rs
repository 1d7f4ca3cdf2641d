//! Who is calling: bearer-token checks shared by both transports, and the identity that
//! per-client limits are counted against.
//!
//! Tokens are kept only as SHA-256 digests. A presented token is hashed and compared with
//! every configured digest in constant time ([`subtle`]), so neither the comparison nor
//! its length says anything about a token. Tokens never appear in logs, errors or job
//! records: a client is named by a short digest prefix (`token:3fa9c2d41b07`) or, without
//! authentication, by its address (`ip:10.1.2.3`).

use std::net::{IpAddr, SocketAddr};

use sha2::{Digest, Sha256};
use subtle::{ConditionallySelectable, ConstantTimeEq};

use crate::config::Secret;
use crate::error::Error;

/// The identity per-client limits are counted against.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct ClientId(pub String);

impl ClientId {
    fn token(digest: &[u8; 32]) -> ClientId {
        let hex: String = digest[..6].iter().map(|b| format!("{b:02x}")).collect();
        ClientId(format!("token:{hex}"))
    }

    /// A client known only by its address (authentication off).
    pub fn peer(addr: Option<SocketAddr>) -> ClientId {
        match addr.map(|a| a.ip()) {
            Some(IpAddr::V6(v6)) => match v6.to_ipv4_mapped() {
                Some(v4) => ClientId(format!("ip:{v4}")),
                None => ClientId(format!("ip:{v6}")),
            },
            Some(ip) => ClientId(format!("ip:{ip}")),
            None => ClientId("ip:unknown".into()),
        }
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// The accepted bearer tokens (as digests); empty disables authentication.
#[derive(Clone, Default)]
pub struct Tokens {
    digests: Vec<[u8; 32]>,
}

impl std::fmt::Debug for Tokens {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Tokens({} configured)", self.digests.len())
    }
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Tokens {
    pub fn new(secrets: &[Secret]) -> Tokens {
        Tokens { digests: secrets.iter().map(|s| digest(&s.0)).collect() }
    }

    pub fn enabled(&self) -> bool {
        !self.digests.is_empty()
    }

    /// The client presenting `authorization` (the header or metadata value), or why it is
    /// refused. With authentication off every caller is accepted and named by `peer`.
    /// `hint` says where the token goes, for the error message.
    pub fn authenticate(
        &self,
        authorization: Option<&str>,
        peer: Option<SocketAddr>,
        hint: &str,
    ) -> Result<ClientId, Error> {
        if !self.enabled() {
            return Ok(ClientId::peer(peer));
        }
        let Some(token) = bearer(authorization) else {
            return Err(Error::Unauthenticated(format!("missing bearer token ({hint}: Bearer <token>)")));
        };
        let presented = digest(token);
        // Every digest is compared, whichever matches: the time taken does not depend on
        // which token (if any) was presented.
        let mut found = subtle::Choice::from(0u8);
        let mut which = [0u8; 32];
        for d in &self.digests {
            let same = d.ct_eq(&presented);
            found |= same;
            for (w, b) in which.iter_mut().zip(d) {
                *w = u8::conditional_select(w, b, same);
            }
        }
        if bool::from(found) {
            Ok(ClientId::token(&which))
        } else {
            Err(Error::Unauthenticated("invalid bearer token".into()))
        }
    }
}

/// The token of an `Authorization: Bearer <token>` value.
pub fn bearer(value: Option<&str>) -> Option<&str> {
    let v = value?.trim();
    let (scheme, token) = v.split_once(' ')?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tokens() -> Tokens {
        Tokens::new(&[Secret("s3cret".into()), Secret("other".into())])
    }

    #[test]
    fn accepts_each_configured_token_and_names_it_by_digest() {
        let t = tokens();
        let a = t.authenticate(Some("Bearer s3cret"), None, "h").unwrap();
        let b = t.authenticate(Some("bearer   other "), None, "h").unwrap();
        assert_ne!(a, b);
        assert!(a.as_str().starts_with("token:") && a.as_str().len() == "token:".len() + 12, "{a:?}");
        assert!(!a.as_str().contains("s3cret"));
        assert_eq!(a, t.authenticate(Some("Bearer s3cret"), None, "h").unwrap(), "stable");
    }

    #[test]
    fn refuses_wrong_missing_and_malformed_tokens() {
        let t = tokens();
        for bad in [Some("Bearer s3cre"), Some("Bearer s3cretx"), Some("Basic s3cret"), Some("Bearer "), Some("s3cret")]
        {
            let e = t.authenticate(bad, None, "h").unwrap_err();
            assert!(matches!(e, Error::Unauthenticated(_)), "{bad:?}");
        }
        let e = t.authenticate(None, None, "header Authorization").unwrap_err();
        assert!(e.to_string().contains("missing bearer token (header Authorization"), "{e}");
        assert!(!format!("{t:?}").contains("s3cret"));
    }

    #[test]
    fn without_tokens_clients_are_named_by_address() {
        let t = Tokens::new(&[]);
        let v4: SocketAddr = "10.1.2.3:4000".parse().unwrap();
        let mapped: SocketAddr = "[::ffff:10.1.2.3]:4001".parse().unwrap();
        assert_eq!(t.authenticate(None, Some(v4), "h").unwrap().as_str(), "ip:10.1.2.3");
        assert_eq!(t.authenticate(Some("Bearer x"), Some(mapped), "h").unwrap().as_str(), "ip:10.1.2.3");
        assert_eq!(t.authenticate(None, None, "h").unwrap().as_str(), "ip:unknown");
    }
}
