//! The two calls of Prometheus's HTTP API that drawing a dashboard needs: a range query
//! (`/api/v1/query_range`, a panel's series) and a label's values (`/api/v1/label/<name>/values`,
//! a `label_values` variable's choices), over plain HTTP.

use std::collections::BTreeMap;
use std::time::Duration;

use serde::de::DeserializeOwned;
use serde::Deserialize;

use crate::grafana::LabelValues;

/// Long enough for a range query over days on a busy server; a server that does not answer at
/// all is told apart at once by a refused connection.
const TIMEOUT: Duration = Duration::from_secs(60);

#[derive(Debug, thiserror::Error)]
pub enum PrometheusError {
    #[error("cannot reach Prometheus at {url}: {cause}")]
    Unreachable { url: String, cause: String },
    #[error("{url}: HTTP {status}, not an answer of Prometheus's API: {body}")]
    NotTheApi {
        url: String,
        status: u16,
        body: String,
    },
    #[error("Prometheus at {url} rejected `{expr}`: {error}")]
    Rejected {
        url: String,
        expr: String,
        error: String,
    },
}

/// The times a range query covers, in Unix seconds, and the spacing of its points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    pub start: f64,
    pub end: f64,
    pub step: f64,
}

/// One series of a range query: its labels and its (Unix seconds, value) points.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub labels: BTreeMap<String, String>,
    pub points: Vec<(f64, f64)>,
}

/// A Prometheus server's HTTP API at a base URL such as `http://127.0.0.1:9090`.
pub struct Prometheus {
    url: String,
    agent: ureq::Agent,
}

#[derive(Deserialize)]
struct Answer<T> {
    status: String,
    data: Option<T>,
    #[serde(rename = "errorType", default)]
    error_type: String,
    #[serde(default)]
    error: String,
}

#[derive(Deserialize)]
struct Matrix {
    result: Vec<RawSeries>,
}

#[derive(Deserialize)]
struct RawSeries {
    metric: BTreeMap<String, String>,
    /// Values are strings in the API: "1.5", "NaN", "+Inf".
    values: Vec<(f64, String)>,
}

impl Prometheus {
    pub fn new(url: &str) -> Prometheus {
        let agent = ureq::Agent::config_builder()
            // Prometheus answers a bad query with 400 and a JSON body naming the error.
            .http_status_as_error(false)
            .timeout_global(Some(TIMEOUT))
            .build()
            .into();
        Prometheus {
            url: url.trim_end_matches('/').to_string(),
            agent,
        }
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// The series `expr` returns at each step of `window`, ordered by their labels.
    pub fn query_range(&self, expr: &str, window: &Window) -> Result<Vec<Series>, PrometheusError> {
        let params = [
            ("query", expr.to_string()),
            ("start", window.start.to_string()),
            ("end", window.end.to_string()),
            ("step", window.step.to_string()),
        ];
        let mut matrix: Matrix = self.get("/api/v1/query_range", &params, expr)?;
        matrix.result.sort_by(|a, b| a.metric.cmp(&b.metric));
        Ok(matrix
            .result
            .into_iter()
            .map(|series| Series {
                labels: series.metric,
                points: series
                    .values
                    .into_iter()
                    // Prometheus writes only numbers, NaN and +-Inf, all of which parse.
                    .map(|(t, v)| (t, v.parse().unwrap_or(f64::NAN)))
                    .collect(),
            })
            .collect())
    }

    /// The values `query.label` takes in `window`, on the series of `query.selector` or on all.
    pub fn label_values(
        &self,
        query: &LabelValues,
        window: &Window,
    ) -> Result<Vec<String>, PrometheusError> {
        let mut params = vec![
            ("start", window.start.to_string()),
            ("end", window.end.to_string()),
        ];
        params.extend(query.selector.iter().map(|s| ("match[]", s.clone())));
        let path = format!("/api/v1/label/{}/values", query.label);
        self.get(&path, &params, &query.to_string())
    }

    /// `GET path?params`, its `data` when Prometheus answers with success; `expr` is what the
    /// call asked, for messages.
    fn get<T: DeserializeOwned>(
        &self,
        path: &str,
        params: &[(&str, String)],
        expr: &str,
    ) -> Result<T, PrometheusError> {
        let url = format!("{}{path}", self.url);
        let unreachable = |cause: ureq::Error| PrometheusError::Unreachable {
            url: self.url.clone(),
            cause: cause.to_string(),
        };
        let mut response = self
            .agent
            .get(&url)
            .query_pairs(params.iter().map(|(k, v)| (*k, v.as_str())))
            .call()
            .map_err(unreachable)?;
        let status = response.status().as_u16();
        let body = response.body_mut().read_to_string().map_err(unreachable)?;
        let not_the_api = || PrometheusError::NotTheApi {
            url: url.clone(),
            status,
            body: body.chars().take(200).collect(),
        };
        let answer: Answer<T> = serde_json::from_str(&body).map_err(|_| not_the_api())?;
        match (answer.status.as_str(), answer.data) {
            ("success", Some(data)) => Ok(data),
            ("error", _) => Err(PrometheusError::Rejected {
                url: self.url.clone(),
                expr: expr.to_string(),
                error: format!("{}: {}", answer.error_type, answer.error),
            }),
            _ => Err(not_the_api()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_closed_port_is_unreachable_and_named() {
        // A port just freed: nothing listens on it.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .unwrap()
            .port();
        let url = format!("http://127.0.0.1:{port}");
        let window = Window {
            start: 0.0,
            end: 60.0,
            step: 15.0,
        };
        let error = Prometheus::new(&url)
            .query_range("up", &window)
            .unwrap_err();
        assert!(
            matches!(error, PrometheusError::Unreachable { .. }),
            "{error:?}"
        );
        assert!(
            error
                .to_string()
                .starts_with(&format!("cannot reach Prometheus at {url}: ")),
            "{error}"
        );
    }
}
