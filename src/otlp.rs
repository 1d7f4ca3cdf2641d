//! Optional OpenTelemetry traces, exported over OTLP/gRPC (`serve --otlp-endpoint`).
//!
//! The daemon's own spans become OpenTelemetry spans (through `tracing-opentelemetry`):
//! every HTTP request (`http.request`: method, route, status, and the `job_id` of a
//! submission or a job's route), and every run of a job (`job`: `job_id`, attempt, worker,
//! variant) with its stages as children (`decode`, `denoise`, `encode`). A submission that
//! carries a W3C `traceparent` header continues the client's trace: the request span is its
//! child, and the job's span (run later, on a worker) is the request's child, through the
//! `traceparent` kept with the job. Spans are batched and sent in the background; a
//! collector that is down costs the daemon nothing but the dropped spans (logged by the
//! exporter). Without `--otlp-endpoint` nothing is set up and no span leaves the process.

use std::collections::HashMap;
use std::time::Duration;

use anyhow::Context;
use opentelemetry::propagation::TextMapPropagator;
use opentelemetry::trace::TracerProvider as _;
use opentelemetry::KeyValue;
use opentelemetry_otlp::WithExportConfig;
use opentelemetry_sdk::propagation::TraceContextPropagator;
use opentelemetry_sdk::trace::{SdkTracerProvider, Tracer};
use opentelemetry_sdk::Resource;
use tracing_opentelemetry::OpenTelemetrySpanExt;

/// The exporter's pipeline; [`Traces::shutdown`] sends what is still batched.
pub struct Traces {
    provider: SdkTracerProvider,
}

/// Starts the OTLP/gRPC exporter to `endpoint` (e.g. `http://otel-collector:4317`). Must be
/// called inside the tokio runtime that serves the daemon (the exporter's connection runs
/// on it).
pub fn start(endpoint: &str, service_name: &str) -> anyhow::Result<(Traces, Tracer)> {
    let exporter = opentelemetry_otlp::SpanExporter::builder()
        .with_tonic()
        .with_endpoint(endpoint)
        .with_timeout(Duration::from_secs(5))
        .build()
        .with_context(|| format!("cannot set up the OTLP exporter to {endpoint}"))?;
    let resource = Resource::builder()
        .with_service_name(service_name.to_string())
        .with_attribute(KeyValue::new("service.version", env!("CARGO_PKG_VERSION")))
        .build();
    let provider = SdkTracerProvider::builder().with_batch_exporter(exporter).with_resource(resource).build();
    let tracer = provider.tracer("mcdenoise");
    Ok((Traces { provider }, tracer))
}

impl Traces {
    /// Sends the spans still batched and stops the exporter.
    pub fn shutdown(self) {
        if let Err(e) = self.provider.shutdown() {
            tracing::warn!(error = %e, "OTLP exporter shutdown");
        }
    }
}

/// The current span's context as a W3C `traceparent` value; `None` when traces are off or
/// the span is not sampled.
pub fn current_traceparent() -> Option<String> {
    let cx = tracing::Span::current().context();
    let mut carrier = HashMap::new();
    TraceContextPropagator::new().inject_context(&cx, &mut carrier);
    carrier.remove("traceparent")
}

/// Makes `span` a child of the context in a `traceparent` (and `tracestate`) pair; an
/// absent or malformed value leaves it a root.
pub fn continue_trace(span: &tracing::Span, traceparent: Option<&str>, tracestate: Option<&str>) {
    let Some(parent) = traceparent else { return };
    let mut carrier = HashMap::from([("traceparent".to_string(), parent.to_string())]);
    if let Some(state) = tracestate {
        carrier.insert("tracestate".to_string(), state.to_string());
    }
    let cx = TraceContextPropagator::new().extract(&carrier);
    use opentelemetry::trace::TraceContextExt;
    if cx.span().span_context().is_valid() {
        let _ = span.set_parent(cx);
    }
}
