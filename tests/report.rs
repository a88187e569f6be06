//! report.html as its readers get it: every run in the sortable table, every drawn run with
//! its five plots, failures with their error, and the page opened in a real headless
//! Chromium, which must load it without script errors and draw every plot.
//!
//! Chromium comes from `scripts/install-deps.sh`. Where it cannot be installed, set
//! `SKELID_SKIP_BROWSER=1` to skip only the browser half (the test says so loudly).

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn skelid() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skelid"))
}

/// Plots per drawn run: envelope, frequency, backbone, restoring force, damping force.
const PLOTS_PER_RUN: usize = 5;
/// Campaign-level plots: clearance and stiffness per row.
const CAMPAIGN_PLOTS: usize = 2;

fn browser() -> Option<String> {
    if let Ok(b) = std::env::var("SKELID_CHROMIUM") {
        return Some(b);
    }
    ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find(|b| {
            Command::new(b)
                .arg("--version")
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()
                .is_ok_and(|s| s.success())
        })
        .map(String::from)
}

/// Opens the page in headless Chromium and returns the `data-check` its script wrote.
fn browser_check(page: &Path) -> Option<String> {
    if std::env::var_os("SKELID_SKIP_BROWSER").is_some() {
        eprintln!("SKELID_SKIP_BROWSER is set: report.html was NOT opened in a browser");
        return None;
    }
    let b = browser().expect(
        "no Chromium found: run scripts/install-deps.sh (it installs chromium), set \
         SKELID_CHROMIUM to a Chromium binary, or SKELID_SKIP_BROWSER=1 to skip this check",
    );
    let profile = tempfile::tempdir().unwrap();
    // The DOM goes to a file: a pipe would fill up (the page is larger than its buffer)
    // while this thread waits for the browser.
    let dom_file = profile.path().join("dom.html");
    let mut child = Command::new(&b)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--virtual-time-budget=10000",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg(format!("file://{}", page.canonicalize().unwrap().display()))
        .stdout(std::fs::File::create(&dom_file).unwrap())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > Duration::from_secs(120) {
            child.kill().ok();
            panic!("{b} did not finish loading the report within 120 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let dom = std::fs::read_to_string(&dom_file).unwrap();
    let start = dom
        .find("data-check=\"")
        .unwrap_or_else(|| panic!("the page's self-check did not run in {b}"));
    let rest = &dom[start + 12..];
    Some(rest[..rest.find('"').unwrap()].to_string())
}

/// A folder holding the demo campaign and its outputs (report.html included).
fn demo() -> tempfile::TempDir {
    let d = tempfile::tempdir().unwrap();
    let out = skelid()
        .args(["demo", "--out"])
        .arg(d.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    d
}

#[test]
fn report_lists_every_run_draws_every_plot_and_opens_in_chromium() {
    let d = demo();
    let page = d.path().join("report.html");
    let html = std::fs::read_to_string(&page).unwrap();

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("summary.json")).unwrap())
            .unwrap();
    let rows = summary["rows"].as_array().unwrap();
    let runs = skelid::demo::cases().len();
    assert_eq!(rows.len(), 2 * runs);
    // Every row × method in the table, failed ones with their error.
    assert_eq!(
        html.matches("<tr class=\"ok\">").count() + html.matches("<tr class=\"failed\">").count(),
        rows.len()
    );
    for r in rows.iter().filter(|r| r["status"] == "failed") {
        let error = r["error"].as_str().unwrap();
        let cut: String = error.chars().take(40).collect();
        assert!(html.contains(&cut), "failed row's error missing: {error}");
    }
    // Every run drawn (the demo draws all), every one of them identified by some method.
    assert_eq!(html.matches("<section id=\"run-").count(), runs);
    // Each run's rows link to its own section (two rows per run: both methods).
    for i in 0..runs {
        assert_eq!(
            html.matches(&format!("<a href=\"#run-{i}\">")).count(),
            2,
            "run {i}"
        );
    }
    let expected = CAMPAIGN_PLOTS + PLOTS_PER_RUN * runs;
    assert!(
        html.contains(&format!("data-plots=\"{expected}\"")),
        "the page does not announce {expected} plots"
    );
    assert_eq!(
        html.matches("<figure class=\"plot\"><svg").count(),
        expected
    );
    // Self-contained: nothing fetched from elsewhere.
    for external in ["src=\"http", "href=\"http", "<link ", "@import"] {
        assert!(
            !html.contains(external),
            "the page loads something: {external}"
        );
    }

    if let Some(check) = browser_check(&page) {
        println!("Chromium's self-check of report.html: {check}");
        assert_eq!(
            check,
            format!("expected={expected} found={expected} drawn={expected} errors=0"),
            "Chromium's view of the page"
        );
    }
}

#[test]
fn report_runs_limits_the_drawn_runs_but_not_the_table() {
    let d = demo();
    let again = d.path().join("again");
    let out = skelid()
        .arg("run")
        .arg(d.path().join("demo_campaign.h5"))
        // One worker thread (`--jobs 1`, the memory bound) gives the same table.
        .args(["--quiet", "--jobs", "1", "--report-runs", "2", "--out"])
        .arg(&again)
        .output()
        .unwrap();
    // The demo's free decay fails with the Hilbert method only, so the run is ok.
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let html = std::fs::read_to_string(again.join("report.html")).unwrap();
    let runs = skelid::demo::cases().len();
    assert_eq!(html.matches("<section id=\"run-").count(), 2);
    assert!(html.contains(&format!("{} more run(s) are in the table", runs - 2)));
    assert_eq!(html.matches("<tr class=").count(), 2 * runs);
    let expected = CAMPAIGN_PLOTS + PLOTS_PER_RUN * 2;
    assert!(html.contains(&format!("data-plots=\"{expected}\"")));
    // Same runs, methods and clearances (to 1e-9: a run identified twice may differ in its
    // last bit).
    let rows = |dir: &Path| -> Vec<(String, String, f64)> {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap())
                .unwrap();
        v["rows"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                (
                    r["run"].to_string(),
                    r["method"].to_string(),
                    r["clearance"].as_f64().unwrap_or(f64::NAN),
                )
            })
            .collect()
    };
    let (a, b) = (rows(&again), rows(d.path()));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!((&x.0, &x.1), (&y.0, &y.1));
        assert!(
            (x.2 - y.2).abs() <= 1e-9 * y.2.abs() || (x.2.is_nan() && y.2.is_nan()),
            "{x:?} vs {y:?}"
        );
    }
}
