//! [`Error`] as an HTTP response: status, JSON body `{"error": {"code", "message"}}`,
//! `Retry-After` on 429, `WWW-Authenticate` on 401.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;

use crate::error::Error;

/// An [`Error`] on its way to an HTTP client.
#[derive(Debug)]
pub struct ApiError(pub Error);

impl From<Error> for ApiError {
    fn from(e: Error) -> Self {
        ApiError(e)
    }
}

/// The HTTP status of each error (exhaustive: a new variant must be mapped here).
pub fn status(e: &Error) -> StatusCode {
    match e {
        Error::BadRequest(_) => StatusCode::BAD_REQUEST,
        Error::InvalidFrame(_) => StatusCode::UNPROCESSABLE_ENTITY,
        Error::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
        Error::Timeout(_) => StatusCode::REQUEST_TIMEOUT,
        Error::Unauthenticated(_) => StatusCode::UNAUTHORIZED,
        Error::Forbidden(_) => StatusCode::FORBIDDEN,
        Error::NotFound(_) => StatusCode::NOT_FOUND,
        Error::Conflict(_) => StatusCode::CONFLICT,
        Error::InProgress(_) => StatusCode::CONFLICT,
        Error::QueueFull { .. } | Error::ClientLimit { .. } => StatusCode::TOO_MANY_REQUESTS,
        Error::Unavailable(_) | Error::Storage { .. } => StatusCode::SERVICE_UNAVAILABLE,
        Error::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let e = self.0;
        let code = status(&e);
        if code == StatusCode::INTERNAL_SERVER_ERROR {
            tracing::error!(error = %e, "request failed");
        }
        let body = Json(json!({ "error": { "code": e.code(), "message": e.to_string() } }));
        let mut response = (code, body).into_response();
        match &e {
            Error::QueueFull { retry_after_s, .. } | Error::ClientLimit { retry_after_s, .. } => {
                response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(*retry_after_s));
            }
            Error::Unavailable(_) | Error::Storage { .. } => {
                response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(5u64));
            }
            Error::Unauthenticated(_) => {
                response
                    .headers_mut()
                    .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"mcdenoise\""));
            }
            Error::BadRequest(_)
            | Error::InvalidFrame(_)
            | Error::TooLarge(_)
            | Error::Timeout(_)
            | Error::Forbidden(_)
            | Error::NotFound(_)
            | Error::Conflict(_)
            | Error::InProgress(_)
            | Error::Internal(_) => {}
        }
        response
    }
}
