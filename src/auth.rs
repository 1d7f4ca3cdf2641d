//! Who is calling: bearer-token checks shared by both transports, and the identity that
//! per-client limits are counted against.
//!
//! Tokens are kept only as SHA-256 digests. A presented token is hashed and compared with
//! every configured digest in constant time ([`subtle`]), so neither the comparison nor
//! its length says anything about a token. Tokens never appear in logs, errors or job
//! records: a client is named by a short digest prefix (`token:3fa9c2d41b07`) or, without
//! authentication, by its address (`ip:10.1.2.3`).
//!
//! Scopes: a `submit` token (`--auth-token`, for render nodes) sees and changes only the
//! jobs it submitted: other jobs answer 404, as if they did not exist. An `operator` token
//! (`--operator-token`, for farm managers and dashboards) sees and changes every job. When
//! operator tokens are configured, `/metrics` needs one; otherwise any token reads it, so a
//! single-token setup works as before. Without authentication every caller is an operator
//! (the daemon then trusts its network, docs/threat-model.md).

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

/// What a token may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scope {
    /// Submit jobs and see, cancel, delete and download its own.
    Submit,
    /// Everything: every client's jobs, and the metrics.
    Operator,
}

impl Scope {
    pub fn name(self) -> &'static str {
        match self {
            Scope::Submit => "submit",
            Scope::Operator => "operator",
        }
    }
}

/// Who is calling and what it may do: set on every authenticated request.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Caller {
    pub id: ClientId,
    pub scope: Scope,
    /// Whether `/metrics` is open to it (operators; anyone while no operator token exists).
    pub metrics: bool,
}

impl Caller {
    /// A caller allowed everything: the daemon's own tasks and tests.
    pub fn operator(id: ClientId) -> Caller {
        Caller { id, scope: Scope::Operator, metrics: true }
    }

    /// Whether it may see and change a job submitted by `owner` (see [`owns`]).
    pub fn may_access(&self, owner: Option<&str>) -> bool {
        self.scope == Scope::Operator || owns(self.id.as_str(), owner)
    }

    /// The owner a listing is restricted to: none for operators.
    pub fn owner_filter(&self) -> Option<String> {
        (self.scope != Scope::Operator).then(|| self.id.as_str().to_string())
    }
}

/// Whether `client` owns a job submitted by `owner` (records written before jobs had owners
/// have none and belong to every client).
pub fn owns(client: &str, owner: Option<&str>) -> bool {
    owner.is_none_or(|o| o == client)
}

/// The accepted bearer tokens (as digests, with their scopes); empty disables
/// authentication.
#[derive(Clone, Default)]
pub struct Tokens {
    digests: Vec<([u8; 32], Scope)>,
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
    /// `submit` tokens and `operator` tokens. A token listed in both is an operator.
    pub fn new(submit: &[Secret], operator: &[Secret]) -> Tokens {
        let operators: Vec<[u8; 32]> = operator.iter().map(|s| digest(&s.0)).collect();
        let submitters = submit.iter().map(|s| digest(&s.0)).filter(|d| !operators.contains(d));
        Tokens {
            digests: submitters
                .map(|d| (d, Scope::Submit))
                .chain(operators.iter().map(|d| (*d, Scope::Operator)))
                .collect(),
        }
    }

    fn has_operators(&self) -> bool {
        self.digests.iter().any(|(_, s)| *s == Scope::Operator)
    }

    pub fn enabled(&self) -> bool {
        !self.digests.is_empty()
    }

    /// The client presenting `authorization` (the header or metadata value), or why it is
    /// refused. With authentication off every caller is accepted as an operator named by
    /// `peer`. `hint` says where the token goes, for the error message.
    pub fn authenticate(
        &self,
        authorization: Option<&str>,
        peer: Option<SocketAddr>,
        hint: &str,
    ) -> Result<Caller, Error> {
        if !self.enabled() {
            return Ok(Caller::operator(ClientId::peer(peer)));
        }
        let Some(token) = bearer(authorization) else {
            return Err(Error::Unauthenticated(format!("missing bearer token ({hint}: Bearer <token>)")));
        };
        let presented = digest(token);
        // Every digest is compared, whichever matches: the time taken does not depend on
        // which token (if any) was presented.
        let mut found = subtle::Choice::from(0u8);
        let mut which = [0u8; 32];
        let mut operator = subtle::Choice::from(0u8);
        for (d, scope) in &self.digests {
            let same = d.ct_eq(&presented);
            found |= same;
            operator |= same & subtle::Choice::from(u8::from(*scope == Scope::Operator));
            for (w, b) in which.iter_mut().zip(d) {
                *w = u8::conditional_select(w, b, same);
            }
        }
        if bool::from(found) {
            let scope = if bool::from(operator) { Scope::Operator } else { Scope::Submit };
            let metrics = scope == Scope::Operator || !self.has_operators();
            Ok(Caller { id: ClientId::token(&which), scope, metrics })
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
        Tokens::new(&[Secret("s3cret".into()), Secret("other".into())], &[])
    }

    #[test]
    fn accepts_each_configured_token_and_names_it_by_digest() {
        let t = tokens();
        let a = t.authenticate(Some("Bearer s3cret"), None, "h").unwrap();
        let b = t.authenticate(Some("bearer   other "), None, "h").unwrap();
        assert_ne!(a, b);
        let name = a.id.as_str();
        assert!(name.starts_with("token:") && name.len() == "token:".len() + 12, "{a:?}");
        assert!(!name.contains("s3cret"));
        // Without operator tokens a submit token reads the metrics, as before scopes.
        assert_eq!((a.scope, a.metrics), (Scope::Submit, true));
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
        let t = Tokens::new(&[], &[]);
        let v4: SocketAddr = "10.1.2.3:4000".parse().unwrap();
        let mapped: SocketAddr = "[::ffff:10.1.2.3]:4001".parse().unwrap();
        let caller = t.authenticate(None, Some(v4), "h").unwrap();
        assert_eq!(caller.id.as_str(), "ip:10.1.2.3");
        assert_eq!(caller.scope, Scope::Operator, "without authentication the network is trusted");
        assert_eq!(t.authenticate(Some("Bearer x"), Some(mapped), "h").unwrap().id.as_str(), "ip:10.1.2.3");
        assert_eq!(t.authenticate(None, None, "h").unwrap().id.as_str(), "ip:unknown");
    }

    #[test]
    fn scopes_decide_whose_jobs_and_the_metrics() {
        let t = Tokens::new(
            &[Secret("node".into()), Secret("both".into())],
            &[Secret("ops".into()), Secret("both".into())],
        );
        let node = t.authenticate(Some("Bearer node"), None, "h").unwrap();
        let ops = t.authenticate(Some("Bearer ops"), None, "h").unwrap();
        assert_eq!((node.scope, node.metrics), (Scope::Submit, false));
        assert_eq!((ops.scope, ops.metrics), (Scope::Operator, true));
        assert_eq!(t.authenticate(Some("Bearer both"), None, "h").unwrap().scope, Scope::Operator);
        assert!(node.may_access(Some(node.id.as_str())) && node.may_access(None));
        assert!(!node.may_access(Some(ops.id.as_str())));
        assert!(ops.may_access(Some(node.id.as_str())));
        assert_eq!(node.owner_filter().as_deref(), Some(node.id.as_str()));
        assert_eq!(ops.owner_filter(), None);
    }
}
