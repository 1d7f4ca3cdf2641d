//! A streaming `multipart/form-data` reader (RFC 7578) that never holds more than a
//! bounded amount of the body in memory.
//!
//! `multer` (behind axum's `Multipart`) buffers the preamble and each part's headers until
//! it finds their end, with no bound: a 300 MiB preamble costs 300 MiB. Here the preamble
//! and the header block of each part have their own limits, checked as bytes arrive; part
//! data is handed out as it arrives, keeping back only the few bytes that could be the
//! start of the next delimiter. What a caller keeps of a part (the `options` JSON) it
//! bounds itself ([`FormData::read_to_limit`]).
//!
//! Memory held: one body chunk (hyper reads at most a few hundred KiB at a time) plus the
//! preamble or header limit.

use bytes::{Buf, Bytes, BytesMut};
use futures_util::{Stream, StreamExt};

/// What the reader keeps in memory at most, besides one body chunk.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Bytes before the first delimiter (RFC 2046's preamble; clients send none).
    pub preamble: usize,
    /// The header block of one part.
    pub headers: usize,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits { preamble: 16 * 1024, headers: 16 * 1024 }
    }
}

/// Why a body could not be read.
#[derive(Debug, PartialEq, Eq)]
pub enum FormError {
    /// Something was over its limit: what, and the limit in bytes.
    TooLarge { what: String, limit: usize },
    /// Not multipart/form-data as RFC 7578 describes it.
    Malformed(String),
    /// The body itself failed (the client went away, a timeout).
    Body(String),
}

impl std::fmt::Display for FormError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FormError::TooLarge { what, limit } => write!(f, "{what} is over its limit of {limit} bytes"),
            FormError::Malformed(m) => write!(f, "bad multipart body: {m}"),
            FormError::Body(m) => write!(f, "the upload was interrupted: {m}"),
        }
    }
}

/// The boundary of a `multipart/form-data` content type, if it names one.
pub fn boundary(content_type: &str) -> Option<String> {
    let (mime, params) = content_type.split_once(';')?;
    if !mime.trim().eq_ignore_ascii_case("multipart/form-data") {
        return None;
    }
    params.split(';').find_map(|p| {
        let (k, v) = p.split_once('=')?;
        if !k.trim().eq_ignore_ascii_case("boundary") {
            return None;
        }
        let v = v.trim().trim_matches('"');
        // RFC 2046: 1 to 70 characters.
        (!v.is_empty() && v.len() <= 70).then(|| v.to_string())
    })
}

/// The headers of one part that matter here.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct PartHead {
    /// The `name` of its `Content-Disposition: form-data`.
    pub name: Option<String>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stage {
    /// Before the first delimiter; counts the bytes skipped.
    Preamble(usize),
    /// Just after a delimiter: `--` (the end) or the part's headers follow.
    Delimiter,
    /// Inside a part's data.
    Data,
    /// After the closing delimiter (the epilogue is not read).
    Done,
}

/// Reads the parts of a body one after the other: [`FormData::next_part`], then
/// [`FormData::chunk`] until `None` (or `next_part` again, which skips the rest).
pub struct FormData<S> {
    body: S,
    buf: BytesMut,
    /// `\r\n--boundary`.
    delimiter: Vec<u8>,
    finder: memchr::memmem::Finder<'static>,
    stage: Stage,
    eof: bool,
    limits: Limits,
    parts: usize,
}

impl<S, E> FormData<S>
where
    S: Stream<Item = Result<Bytes, E>> + Unpin,
    E: std::fmt::Display,
{
    pub fn new(body: S, boundary: &str, limits: Limits) -> FormData<S> {
        let delimiter = format!("\r\n--{boundary}").into_bytes();
        let finder = memchr::memmem::Finder::new(&delimiter).into_owned();
        // The first delimiter may open the body, without the CRLF in front.
        let buf = BytesMut::from(&b"\r\n"[..]);
        FormData { body, buf, delimiter, finder, stage: Stage::Preamble(0), eof: false, limits, parts: 0 }
    }

    /// Reads one more chunk of the body into the buffer; `false` at its end.
    async fn fill(&mut self) -> Result<bool, FormError> {
        if self.eof {
            return Ok(false);
        }
        match self.body.next().await {
            Some(Ok(chunk)) => {
                self.buf.extend_from_slice(&chunk);
                Ok(true)
            }
            Some(Err(e)) => Err(FormError::Body(e.to_string())),
            None => {
                self.eof = true;
                Ok(false)
            }
        }
    }

    /// The next piece of data before the next delimiter (`None` once the delimiter is
    /// reached and consumed).
    async fn data(&mut self) -> Result<Option<Bytes>, FormError> {
        loop {
            if let Some(at) = self.finder.find(&self.buf) {
                if at > 0 {
                    return Ok(Some(self.buf.split_to(at).freeze()));
                }
                self.buf.advance(self.delimiter.len());
                self.stage = Stage::Delimiter;
                return Ok(None);
            }
            // Everything but a possible start of the delimiter can go.
            let keep = self.delimiter.len() - 1;
            if self.buf.len() > keep {
                let n = self.buf.len() - keep;
                return Ok(Some(self.buf.split_to(n).freeze()));
            }
            if !self.fill().await? {
                return Err(FormError::Malformed(match self.stage {
                    Stage::Preamble(_) => "no boundary delimiter found".into(),
                    _ => format!("the body ended inside part {}", self.parts),
                }));
            }
        }
    }

    /// Moves to the next part (skipping what is left of the current one) and reads its
    /// headers; `None` after the closing delimiter.
    pub async fn next_part(&mut self) -> Result<Option<PartHead>, FormError> {
        loop {
            match self.stage {
                Stage::Done => return Ok(None),
                Stage::Preamble(skipped) => match self.data().await? {
                    Some(bytes) => {
                        let skipped = skipped + bytes.len();
                        if skipped > self.limits.preamble + 2 {
                            return Err(FormError::TooLarge {
                                what: "the multipart preamble (the bytes before the first boundary)".into(),
                                limit: self.limits.preamble,
                            });
                        }
                        self.stage = Stage::Preamble(skipped);
                    }
                    None => {}
                },
                Stage::Data => while self.data().await?.is_some() {},
                Stage::Delimiter => return self.head().await,
            }
        }
    }

    /// After a delimiter: the closing `--`, or transport padding, CRLF and the headers.
    async fn head(&mut self) -> Result<Option<PartHead>, FormError> {
        self.parts += 1;
        let part = self.parts;
        let what = move || format!("the headers of multipart part {part}");
        loop {
            if self.buf.starts_with(b"--") {
                self.stage = Stage::Done;
                return Ok(None);
            }
            let padding = self.buf.iter().take_while(|b| **b == b' ' || **b == b'\t').count();
            let rest = &self.buf[padding..];
            if rest.len() >= 2 && !rest.starts_with(b"\r\n") {
                return Err(FormError::Malformed("a boundary delimiter not followed by a line break".into()));
            }
            if rest.len() >= 2 {
                // The header block runs from this CRLF to the first empty line.
                if let Some(end) = memchr::memmem::find(rest, b"\r\n\r\n") {
                    // `end` is 0 when the part has no headers at all.
                    let head = parse_head(rest.get(2..end).unwrap_or_default())?;
                    self.buf.advance(padding + end + 4);
                    self.stage = Stage::Data;
                    return Ok(Some(head));
                }
            }
            if self.buf.len() > self.limits.headers + 4 {
                return Err(FormError::TooLarge { what: what(), limit: self.limits.headers });
            }
            if !self.fill().await? {
                return Err(FormError::Malformed(format!("the body ended inside {}", what())));
            }
        }
    }

    /// The next piece of the current part's data; `None` at its end.
    pub async fn chunk(&mut self) -> Result<Option<Bytes>, FormError> {
        if self.stage != Stage::Data {
            return Ok(None);
        }
        self.data().await
    }

    /// The whole current part, refused as soon as it is over `limit` bytes (`what` names
    /// it in the error).
    pub async fn read_to_limit(&mut self, what: &str, limit: usize) -> Result<Vec<u8>, FormError> {
        let mut out = Vec::new();
        while let Some(chunk) = self.chunk().await? {
            if out.len() + chunk.len() > limit {
                return Err(FormError::TooLarge { what: what.to_string(), limit });
            }
            out.extend_from_slice(&chunk);
        }
        Ok(out)
    }
}

/// The `name` of a part's `Content-Disposition: form-data; name="…"`.
fn parse_head(block: &[u8]) -> Result<PartHead, FormError> {
    let text = String::from_utf8_lossy(block);
    let mut head = PartHead::default();
    for line in text.split("\r\n").filter(|_| !block.is_empty()) {
        let Some((key, value)) = line.split_once(':') else {
            return Err(FormError::Malformed(format!(
                "a part header without a colon: `{}`",
                crate::error::truncate(line, 64)
            )));
        };
        if key.trim().eq_ignore_ascii_case("content-disposition") {
            head.name = disposition_name(value);
        }
    }
    Ok(head)
}

fn disposition_name(value: &str) -> Option<String> {
    let mut params = split_params(value).into_iter();
    let kind = params.next()?;
    if !kind.trim().eq_ignore_ascii_case("form-data") {
        return None;
    }
    params.find_map(|p| {
        let (k, v) = p.split_once('=')?;
        if !k.trim().eq_ignore_ascii_case("name") {
            return None;
        }
        let v = v.trim();
        Some(match v.strip_prefix('"').and_then(|v| v.strip_suffix('"')) {
            Some(quoted) => quoted.replace("\\\"", "\"").replace("\\\\", "\\"),
            None => v.to_string(),
        })
    })
}

/// Splits on `;` outside quoted strings.
fn split_params(value: &str) -> Vec<&str> {
    let (mut out, mut start, mut quoted, mut escaped) = (Vec::new(), 0, false, false);
    for (i, c) in value.char_indices() {
        match c {
            _ if escaped => escaped = false,
            '\\' if quoted => escaped = true,
            '"' => quoted = !quoted,
            ';' if !quoted => {
                out.push(&value[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    out.push(&value[start..]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    type Body = futures_util::stream::Iter<std::vec::IntoIter<Result<Bytes, std::convert::Infallible>>>;

    /// `data` as a body cut into pieces of `size` bytes.
    fn body(data: &[u8], size: usize) -> Body {
        let chunks: Vec<_> = data.chunks(size.max(1)).map(|c| Ok(Bytes::copy_from_slice(c))).collect();
        futures_util::stream::iter(chunks)
    }

    /// Every part as (name, data).
    async fn parts(data: &[u8], size: usize, limits: Limits) -> Result<Vec<(Option<String>, Vec<u8>)>, FormError> {
        let mut form = FormData::new(body(data, size), "XyZ", limits);
        let mut out = Vec::new();
        while let Some(head) = form.next_part().await? {
            let mut bytes = Vec::new();
            while let Some(c) = form.chunk().await? {
                bytes.extend_from_slice(&c);
            }
            out.push((head.name, bytes));
        }
        Ok(out)
    }

    const FORM: &[u8] = b"preamble\r\n--XyZ\r\nContent-Disposition: form-data; name=\"options\"\r\n\r\n{\"a\":1}\r\n\
        --XyZ  \r\ncontent-disposition: form-data; name=\"fr;a\\\"me\"; filename=\"f.exr\"\r\nContent-Type: image/x-exr\r\n\r\n\
        \r\n--XyY\r--X\r\n--XyZ--\r\nepilogue";

    #[tokio::test]
    async fn parts_come_out_whole_however_the_body_is_cut() {
        let expected = vec![
            (Some("options".to_string()), b"{\"a\":1}".to_vec()),
            (Some("fr;a\"me".to_string()), b"\r\n--XyY\r--X".to_vec()),
        ];
        for size in 1..FORM.len() + 1 {
            assert_eq!(parts(FORM, size, Limits::default()).await.unwrap(), expected, "chunks of {size}");
        }
        // A body that opens with the delimiter, and a part without headers.
        let got = parts(b"--XyZ\r\n\r\nabc\r\n--XyZ--", 3, Limits::default()).await.unwrap();
        assert_eq!(got, vec![(None, b"abc".to_vec())]);
    }

    #[tokio::test]
    async fn the_preamble_and_part_headers_are_refused_past_their_limits() {
        let limits = Limits { preamble: 100, headers: 200 };
        let mut long_preamble = vec![b'p'; 1000];
        long_preamble.extend_from_slice(FORM);
        let err = parts(&long_preamble, 7, limits).await.unwrap_err();
        assert!(matches!(&err, FormError::TooLarge { what, limit: 100 } if what.contains("preamble")), "{err:?}");

        let mut long_header = b"--XyZ\r\nContent-Disposition: form-data; name=\"options\"\r\nX-Pad: ".to_vec();
        long_header.extend(std::iter::repeat_n(b'h', 10_000));
        let err = parts(&long_header, 64, limits).await.unwrap_err();
        assert_eq!(err, FormError::TooLarge { what: "the headers of multipart part 1".into(), limit: 200 });
        // Within the limits, the same shapes parse.
        assert_eq!(parts(FORM, 5, limits).await.unwrap().len(), 2);
    }

    #[tokio::test]
    async fn a_part_read_to_a_limit_stops_at_the_limit() {
        let mut data = b"--XyZ\r\nContent-Disposition: form-data; name=\"options\"\r\n\r\n".to_vec();
        data.extend(std::iter::repeat_n(b'x', 5000));
        // No end: the limit must be hit before the body runs out.
        let mut form = FormData::new(body(&data, 100), "XyZ", Limits::default());
        assert_eq!(form.next_part().await.unwrap().unwrap().name.as_deref(), Some("options"));
        let err = form.read_to_limit("the `options` part", 1000).await.unwrap_err();
        assert_eq!(err, FormError::TooLarge { what: "the `options` part".into(), limit: 1000 });
    }

    #[tokio::test]
    async fn malformed_bodies_are_errors() {
        for (data, what) in [
            (&b"no delimiter at all"[..], "no boundary delimiter"),
            (b"--XyZ\r\nContent-Disposition: form-data; name=\"a\"\r\n\r\nabc", "ended inside part 1"),
            (b"--XyZ\r\nno colon here\r\n\r\nabc\r\n--XyZ--", "without a colon"),
            (b"--XyZx\r\n\r\n\r\n--XyZ--", "not followed by a line break"),
            (b"--XyZ\r\nContent-Disposition: form-data", "ended inside the headers"),
        ] {
            let err = parts(data, 4, Limits::default()).await.unwrap_err();
            assert!(err.to_string().contains(what), "{err} should say {what}");
        }
    }

    #[test]
    fn boundaries_and_truncation() {
        assert_eq!(boundary("multipart/form-data; boundary=abc").as_deref(), Some("abc"));
        assert_eq!(boundary("Multipart/Form-Data; charset=x; Boundary=\"a b\"").as_deref(), Some("a b"));
        assert_eq!(boundary("multipart/form-data"), None);
        assert_eq!(boundary("multipart/mixed; boundary=abc"), None);
        use crate::error::truncate;
        assert_eq!(truncate("abcdef", 3), "abc…");
        assert_eq!(truncate("abc", 3), "abc");
        assert_eq!(truncate("ééé", 2), "éé…");
    }
}
