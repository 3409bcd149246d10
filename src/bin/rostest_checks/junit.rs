//! JUnit XML for rostest: a `<test>` node is started with `--gtest_output=xml:PATH` and
//! rostest counts the test cases it finds in that file (none found = "0 tests", a failure).
//! [`TestReport`] collects named checks and writes the file through `quick-junit`: a
//! `<testsuites>` holding one `<testsuite>` (rostest reads every `<testsuite>` and its
//! `tests`, `failures` and `errors`), one `<testcase>` per check, a `<failure>` (message and
//! text) in each failed one.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use quick_junit::{NonSuccessKind, Report, TestCaseStatus, TestSuite};

/// The result of one named check.
#[derive(Debug, Clone, PartialEq)]
pub struct TestCase {
    /// The check's name (the `testcase` name in the XML).
    pub name: String,
    /// Duration of the check, s.
    pub time_s: f64,
    /// `None` when it passed, else why it failed.
    pub failure: Option<String>,
}

/// A suite of checks that becomes one JUnit `testsuite`.
#[derive(Debug, Clone)]
pub struct TestReport {
    suite: String,
    cases: Vec<TestCase>,
    started: Instant,
}

/// The path from a `--gtest_output=xml:PATH` argument among `args`, if any.
pub fn gtest_output_path<S: AsRef<str>>(args: &[S]) -> Option<PathBuf> {
    args.iter()
        .filter_map(|a| a.as_ref().strip_prefix("--gtest_output=xml:"))
        .find(|p| !p.is_empty())
        .map(PathBuf::from)
}

impl TestReport {
    /// An empty report for the suite `suite`.
    pub fn new(suite: &str) -> Self {
        Self {
            suite: suite.to_string(),
            cases: Vec::new(),
            started: Instant::now(),
        }
    }

    /// Record a check: `result` is `Ok(())` when it passed, else the failure message.
    pub fn record(&mut self, name: &str, time_s: f64, result: Result<(), String>) {
        self.cases.push(TestCase {
            name: name.to_string(),
            time_s,
            failure: result.err(),
        });
    }

    /// Run `check` and record its outcome and duration under `name`.
    pub fn check<F: FnOnce() -> Result<(), String>>(&mut self, name: &str, check: F) {
        let t0 = Instant::now();
        let result = check();
        self.record(name, t0.elapsed().as_secs_f64(), result);
    }

    /// The recorded checks.
    pub fn cases(&self) -> &[TestCase] {
        &self.cases
    }

    /// True when at least one check ran and none failed.
    pub fn passed(&self) -> bool {
        !self.cases.is_empty() && self.cases.iter().all(|c| c.failure.is_none())
    }

    /// The JUnit XML document.
    pub fn to_xml(&self) -> Result<String, quick_junit::SerializeError> {
        let mut suite = TestSuite::new(self.suite.as_str());
        suite.set_time(self.started.elapsed());
        for c in &self.cases {
            let status = match &c.failure {
                None => TestCaseStatus::success(),
                Some(msg) => {
                    let mut failed = TestCaseStatus::non_success(NonSuccessKind::Failure);
                    failed.set_message(msg.as_str()).set_description(msg.as_str());
                    failed
                }
            };
            let mut case = quick_junit::TestCase::new(c.name.as_str(), status);
            case.set_classname(self.suite.as_str())
                .set_time(Duration::try_from_secs_f64(c.time_s).unwrap_or_default());
            suite.add_test_case(case);
        }
        let mut report = Report::new(self.suite.as_str());
        report.add_test_suite(suite);
        report.to_string()
    }

    /// Write the XML to `path`, creating its folder.
    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let xml = self.to_xml().map_err(std::io::Error::other)?;
        std::fs::write(path, xml)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_gtest_output_argument() {
        let args = ["node", "__name:=x", "--gtest_output=xml:/tmp/a b/r.xml"];
        assert_eq!(gtest_output_path(&args), Some(PathBuf::from("/tmp/a b/r.xml")));
        assert_eq!(gtest_output_path(&["node", "--gtest_output=xml:"]), None);
        assert_eq!(gtest_output_path::<&str>(&[]), None);
    }

    #[test]
    fn xml_counts_failures_and_escapes() {
        let mut r = TestReport::new("suite<1>");
        r.record("ok", 0.5, Ok(()));
        r.record("bad", 1.0, Err("M = 3 > 2 & \"x\"".into()));
        let x = r.to_xml().unwrap();
        assert!(x.contains("<testsuite name=\"suite&lt;1&gt;\" tests=\"2\""), "{x}");
        assert!(x.contains("failures=\"1\""), "{x}");
        assert_eq!(x.matches("<testcase ").count(), 2, "{x}");
        assert_eq!(x.matches("<failure ").count(), 1, "{x}");
        assert!(x.contains("name=\"suite&lt;1&gt;\""), "{x}");
        assert!(x.contains("M = 3 &gt; 2 &amp; &quot;x&quot;"), "{x}");
        assert!(!r.passed());
    }

    #[test]
    fn empty_report_does_not_pass_and_file_is_written() {
        let mut r = TestReport::new("s");
        assert!(!r.passed());
        r.check("passes", || Ok(()));
        assert!(r.passed());
        let dir = std::env::temp_dir().join(format!("junit_test_{}", std::process::id()));
        let path = dir.join("sub/r.xml");
        r.write(&path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("<testcase name=\"passes\" classname=\"s\""), "{text}");
        let _ = std::fs::remove_dir_all(dir);
    }
}
