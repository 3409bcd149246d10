//! Every headline figure is stated once, with its command: in the README's "Headline figures"
//! table, whose rows give each figure beside the command that produced it and link to the docs
//! page that holds the protocol, the configuration and the explanation. The docs pages refer
//! to that table (`../README.md#headline-figures`) instead of restating its numbers.
//!
//! What is checked, on README.md and docs/*.md read from the checkout:
//!
//! 1. every link of the Headline figures table to `docs/X.md#anchor` names a page that exists
//!    and a heading of it whose GitHub anchor is `anchor` (every row has such a link);
//! 2. no row's distinctive figures appear again in docs/*.md, docs/history.md excepted (the
//!    record of superseded figures). A distinctive figure is a decimal number or a range with
//!    its unit ("0.52 N", "3.98 s", "1.55 mm", "69–71 µs") or a count "a/b" with b >= 100
//!    ("498/500"), matched on its text (whitespace collapsed, a range's hyphen read as "–");
//!    `ALLOWED` lists the few that are also another, unrelated figure or a bound, with why;
//! 3. the README's own prose, outside the table, does not restate them either: it points to
//!    the table or to the page;
//! 4. every link between README.md and docs/*.md that names an anchor finds its heading.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Tokens a docs page may hold although a headline row holds the same text: `(token, page,
/// reason)`, the page `docs/NAME.md`, or `""` for every page. Each is a different figure, a
/// bound or a setting, never the headline measurement itself.
const ALLOWED: &[(&str, &str, &str)] = &[
    // The hand-eye error levels the trials are configured with (0.5 mm / 0.2°), and the
    // preflight's residual bound (0.5°): settings and bounds, stated wherever they apply.
    ("0.5 mm", "", "a configured hand-eye error level and a recurring bound"),
    ("0.2°", "", "a configured hand-eye error level and a recurring bound"),
    ("0.5°", "", "the preflight's residual bound and other angle bounds"),
    // The commanded pan speed of the force-stop scenario and of the steering scripts.
    ("0.17 rad/s", "", "a commanded speed, not a measurement"),
    // The withdrawal's force bound, its 12 N stop + 20 %, asserted by tests/force_stop.rs.
    ("14.4 N", "", "a bound, not a measurement"),
    // The rostests' peak-force bound "0.5 / 2.9 N" in docs/ros.md's bounds table (kept
    // exactly, checked by tests/docs_bounds.rs); the trials' max force of seed 4001 is 2.9 N.
    ("2.9 N", "docs/ros.md", "a rostest's bound, not the trials' max force"),
    // The camera trials' counts of the paper's 5 mm test, per seed: other trials than the
    // headline rows whose counts read 100/100.
    (
        "100/100",
        "docs/markerless.md",
        "the camera trials' paper's-test counts",
    ),
    // The dry run's tip distance from the goal (docs/lab.md) and the endoscope test's error
    // along the shaft (docs/markerless.md); the headline's 0.13 mm is the stereo port p95.
    ("0.13 mm", "docs/lab.md", "the dry run's tip distance"),
    (
        "0.13 mm",
        "docs/markerless.md",
        "the endoscope test's error along the shaft",
    ),
    // docking_fused_marker_hidden's refused seal in a clean-clone `make test`; the headline's
    // +10.2 mm is a docking_markerless run.
    ("10.2 mm", "docs/ros.md", "another rostest's refused seal"),
    // The 1 kHz trials' max force (docs/simulation.md, the soak); the headline's 5.4 N is the
    // paper world's at 100 Hz.
    ("5.4 N", "docs/simulation.md", "the 1 kHz trials' max force"),
];

/// The unit that may follow a number in a distinctive figure; longer spellings first.
const UNITS: &[&str] = &[
    "N/m", "mm/s", "rad/s", "µs", "us", "ms", "mm", "kHz", "Hz", "kB", "MB", "min", "deg", "°", "%", "N", "s", "m",
];

/// The checkout's root (where README.md and docs/ are).
fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// GitHub's anchor of a heading: lowercase, spaces to '-', every other character that is not
/// a letter, a digit, '-' or '_' removed.
fn github_anchor(heading: &str) -> String {
    heading
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .flat_map(char::to_lowercase)
        .collect()
}

/// The anchors of a Markdown text's headings (outside fenced code), a repeated anchor
/// numbered "-1", "-2", ... as GitHub does.
fn anchors(markdown: &str) -> BTreeSet<String> {
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut out = BTreeSet::new();
    let mut fenced = false;
    for line in markdown.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        let hashes = line.chars().take_while(|&c| c == '#').count();
        if fenced || !(1..=6).contains(&hashes) || !line[hashes..].starts_with(' ') {
            continue;
        }
        let anchor = github_anchor(line[hashes..].trim().trim_end_matches('#').trim());
        let n = seen.entry(anchor.clone()).or_insert(0);
        out.insert(if *n == 0 { anchor } else { format!("{anchor}-{n}") });
        *n += 1;
    }
    out
}

/// The targets of the Markdown links `[text](target)` in a text.
fn links(text: &str) -> Vec<&str> {
    text.match_indices("](")
        .filter_map(|(i, _)| {
            let rest = &text[i + 2..];
            let end = rest.find(|c: char| c == ')' || c.is_whitespace())?;
            rest[end..].starts_with(')').then(|| &rest[..end])
        })
        .collect()
}

/// The rows of the README's "Headline figures" table (header and separator left out), each
/// as its cells.
fn headline_rows(readme: &str) -> Vec<Vec<String>> {
    let section = readme
        .split("\n## Headline figures\n")
        .nth(1)
        .expect("README.md has the section \"## Headline figures\"");
    let section = section.split("\n## ").next().unwrap();
    section
        .lines()
        .filter(|l| l.starts_with('|'))
        .skip(2)
        .map(|l| {
            let cells: Vec<String> = l.split('|').map(|c| c.trim().to_string()).collect();
            cells[1..cells.len() - 1].to_vec()
        })
        .collect()
}

/// Whether a figure may end before `chars[i]`: not inside a word, a path, a count or a number.
fn ends_here(chars: &[char], i: usize) -> bool {
    match chars.get(i) {
        None => true,
        Some(&c) => {
            !(c.is_alphanumeric()
                || c == '/'
                || c == '_'
                || (c == '.' && chars.get(i + 1).is_some_and(|d| d.is_ascii_digit())))
        }
    }
}

/// The number at `chars[i]` (digits, optionally a '.' and more digits): its end and whether
/// it has decimals.
fn number(chars: &[char], i: usize) -> (usize, bool) {
    let mut j = i;
    while chars.get(j).is_some_and(|c| c.is_ascii_digit()) {
        j += 1;
    }
    if chars.get(j) == Some(&'.') && chars.get(j + 1).is_some_and(|c| c.is_ascii_digit()) {
        j += 1;
        while chars.get(j).is_some_and(|c| c.is_ascii_digit()) {
            j += 1;
        }
        return (j, true);
    }
    (j, false)
}

/// The distinctive figures of a text, in order: a decimal number or a range followed by a
/// unit ("0.52 N", "69–71 µs", "0.2°"; the space before the unit as written, a range's hyphen
/// written "–"), and a count "a/b" with b >= 100. Whitespace (line breaks) reads as one space.
fn figure_tokens(text: &str) -> Vec<String> {
    let chars: Vec<char> = text.split_whitespace().collect::<Vec<_>>().join(" ").chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let starts =
            chars[i].is_ascii_digit() && (i == 0 || !(chars[i - 1].is_alphanumeric() || ".,_/".contains(chars[i - 1])));
        if !starts {
            i += 1;
            continue;
        }
        let (mut j, mut decimal) = number(&chars, i);
        let mut token: String = chars[i..j].iter().collect();
        if !decimal && chars.get(j) == Some(&'/') && chars.get(j + 1).is_some_and(char::is_ascii_digit) {
            let (k, d) = number(&chars, j + 1);
            let below: String = chars[j + 1..k].iter().collect();
            if !d && ends_here(&chars, k) && below.parse::<u64>().is_ok_and(|b| b >= 100) {
                out.push(format!("{token}/{below}"));
            }
            i = k;
            continue;
        }
        let mut range = false;
        if matches!(chars.get(j), Some('-' | '–')) && chars.get(j + 1).is_some_and(char::is_ascii_digit) {
            let (k, d) = number(&chars, j + 1);
            token.push('–');
            token.extend(&chars[j + 1..k]);
            (j, decimal, range) = (k, decimal || d, true);
        }
        let spaced = chars.get(j) == Some(&' ');
        let at = j + usize::from(spaced);
        let unit = UNITS.iter().find(|u| {
            let u: Vec<char> = u.chars().collect();
            chars.get(at..at + u.len()) == Some(&u[..]) && ends_here(&chars, at + u.len())
        });
        if let (Some(unit), true) = (unit, decimal || range) {
            out.push(format!("{token}{}{unit}", if spaced { " " } else { "" }));
        }
        i = j;
    }
    out
}

/// Whether `token` may appear in `page` although a headline row holds it.
fn allowed(token: &str, page: &str) -> bool {
    ALLOWED
        .iter()
        .any(|&(t, p, _)| t == token && (p.is_empty() || p == page))
}

/// The docs pages, as `("docs/NAME.md", text)`.
fn docs_pages(root: &Path) -> Vec<(String, String)> {
    let mut pages: Vec<(String, String)> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().and_then(|e| e.to_str()) == Some("md"))
        .map(|p| {
            let name = format!("docs/{}", p.file_name().unwrap().to_string_lossy());
            (name, read(&p))
        })
        .collect();
    pages.sort();
    pages
}

/// Problems with check 1: the table's links to docs pages and their anchors.
fn headline_link_problems(root: &Path, readme: &str) -> Vec<String> {
    let mut problems = Vec::new();
    for row in headline_rows(readme) {
        let targets: Vec<&str> = row
            .iter()
            .flat_map(|c| links(c))
            .filter(|t| t.starts_with("docs/"))
            .collect();
        if targets.is_empty() {
            problems.push(format!("the row \"{}\" links to no docs page", row[0]));
        }
        for target in targets {
            let (page, anchor) = target.split_once('#').unwrap_or((target, ""));
            let path = root.join(page);
            if !path.exists() {
                problems.push(format!("{target}: no page {page}"));
            } else if !anchor.is_empty() && !anchors(&read(&path)).contains(anchor) {
                problems.push(format!("{target}: {page} has no heading with the anchor #{anchor}"));
            }
        }
    }
    problems
}

/// Problems with check 2: a headline row's distinctive figure restated in a docs page.
fn restated_figure_problems(readme: &str, pages: &[(String, String)]) -> Vec<String> {
    let mut problems = Vec::new();
    let page_tokens: Vec<(&str, Vec<String>)> = pages
        .iter()
        .filter(|(name, _)| name != "docs/history.md")
        .map(|(name, text)| (name.as_str(), figure_tokens(text)))
        .collect();
    for row in headline_rows(readme) {
        let figures: BTreeSet<String> = figure_tokens(&row[1]).into_iter().collect();
        for figure in &figures {
            for (page, tokens) in &page_tokens {
                let n = tokens.iter().filter(|t| *t == figure).count();
                if n > 0 && !allowed(figure, page) {
                    problems.push(format!(
                        "\"{figure}\" (README, Headline figures: {}) appears {n} time(s) in {page}",
                        row[0]
                    ));
                }
            }
        }
    }
    problems
}

/// Problems with check 3: a headline row's distinctive figure restated in the README outside
/// the Headline figures section.
fn readme_prose_problems(readme: &str) -> Vec<String> {
    let (before, after) = readme
        .split_once("\n## Headline figures\n")
        .expect("README.md has the section \"## Headline figures\"");
    let rest = after.split_once("\n## ").map_or("", |(_, rest)| rest);
    let prose = figure_tokens(&format!("{before}\n{rest}"));
    let mut problems = Vec::new();
    for row in headline_rows(readme) {
        for figure in figure_tokens(&row[1]).into_iter().collect::<BTreeSet<_>>() {
            if prose.contains(&figure) && !allowed(&figure, "README.md") {
                problems.push(format!("\"{figure}\" ({}) is restated outside the table", row[0]));
            }
        }
    }
    problems
}

/// Problems with check 4: links between README.md and docs/*.md whose anchor has no heading.
fn anchor_problems(root: &Path, readme: &str, pages: &[(String, String)]) -> Vec<String> {
    let mut texts: Vec<(String, &str)> = vec![("README.md".to_string(), readme)];
    texts.extend(pages.iter().map(|(n, t)| (n.clone(), t.as_str())));
    let anchors_of: BTreeMap<PathBuf, BTreeSet<String>> =
        texts.iter().map(|(n, t)| (root.join(n), anchors(t))).collect();
    let mut problems = Vec::new();
    for (name, text) in &texts {
        let dir = root.join(name).parent().unwrap().to_path_buf();
        for target in links(text) {
            let Some((page, anchor)) = target.split_once('#') else {
                continue;
            };
            if target.contains("://") || !(page.is_empty() || page.ends_with(".md")) {
                continue;
            }
            let path = if page.is_empty() {
                root.join(name)
            } else {
                normalise(&dir.join(page))
            };
            match anchors_of.get(&path) {
                Some(a) if a.contains(anchor) => {}
                Some(_) => problems.push(format!("{name}: ({target}): no heading with that anchor")),
                None if path.exists() => {}
                None => problems.push(format!("{name}: ({target}): no such page")),
            }
        }
    }
    problems
}

/// A path with its "." and ".." components resolved (without touching the file system).
fn normalise(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for part in path.components() {
        match part {
            std::path::Component::ParentDir => {
                out.pop();
            }
            std::path::Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}

#[test]
fn every_headline_link_finds_its_page_and_heading() {
    let root = root();
    let readme = read(&root.join("README.md"));
    assert!(
        headline_rows(&readme).len() >= 10,
        "the Headline figures table has its rows"
    );
    let problems = headline_link_problems(&root, &readme);
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn no_headline_figure_is_restated_in_the_docs() {
    let root = root();
    let readme = read(&root.join("README.md"));
    let problems = restated_figure_problems(&readme, &docs_pages(&root));
    assert!(
        problems.is_empty(),
        "link to the README's row (../README.md#headline-figures) instead of restating:\n{}",
        problems.join("\n")
    );
}

#[test]
fn no_headline_figure_is_restated_in_the_readme_prose() {
    let readme = read(&root().join("README.md"));
    let problems = readme_prose_problems(&readme);
    assert!(
        problems.is_empty(),
        "point to the table (#headline-figures) or to the page instead:\n{}",
        problems.join("\n")
    );
}

/// The allow-list stays small: every entry is a token some headline row holds and some page
/// it names holds too (an entry no longer needed is removed).
#[test]
fn every_allowance_is_still_needed() {
    let root = root();
    let readme = read(&root.join("README.md"));
    let headline: BTreeSet<String> = headline_rows(&readme)
        .iter()
        .flat_map(|r| figure_tokens(&r[1]))
        .collect();
    let pages = docs_pages(&root);
    for &(token, page, reason) in ALLOWED {
        assert!(headline.contains(token), "{token} ({reason}): no headline row holds it");
        let used = pages
            .iter()
            .filter(|(name, _)| page.is_empty() || name == page)
            .any(|(_, text)| figure_tokens(text).iter().any(|t| t == token));
        assert!(used, "{token} ({reason}): {page} no longer holds it");
    }
}

#[test]
fn every_link_between_the_pages_finds_its_heading() {
    let root = root();
    let readme = read(&root.join("README.md"));
    let problems = anchor_problems(&root, &readme, &docs_pages(&root));
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_helpers_read_what_they_are_given() {
    assert_eq!(
        github_anchor("The hand-eye error, 500 trials per arm"),
        "the-hand-eye-error-500-trials-per-arm"
    );
    assert_eq!(
        github_anchor("In the estimator: `method: marker | markerless | fused`"),
        "in-the-estimator-method-marker--markerless--fused"
    );
    let md = "# A\n```sh\n# not a heading\n```\n## A\n### Step timing\n";
    let a = anchors(md);
    assert_eq!(
        a,
        ["a", "a-1", "step-timing"]
            .map(String::from)
            .into_iter()
            .collect::<BTreeSet<_>>()
    );
    assert_eq!(
        links("see [x](docs/a.md#b) and [y](#c), not [z] (d)"),
        ["docs/a.md#b", "#c"]
    );
    assert_eq!(
        figure_tokens(
            "M 0.52 N, 498/500 and 18/100 but 3/20; 69–71 µs, 1.2-1.7\nms, 0.2°, 2 mm, 0.5 Nm, \
             commit 6e5eb97, 2026-12-07, v1.0.5 s, p95 2.72 mm."
        ),
        [
            "0.52 N",
            "498/500",
            "18/100",
            "69–71 µs",
            "1.2–1.7 ms",
            "0.2°",
            "2.72 mm"
        ]
    );
    let readme = "x\n## Headline figures\n\n| what | figure | command | detail |\n|---|---|---|---|\n\
                  | a | 0.52 N | `c` | [p](docs/p.md#q) |\n\n## Next\n| z | 9.9 N | | |\n";
    let rows = headline_rows(readme);
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0][1], "0.52 N");
    let pages = [("docs/p.md".to_string(), "# Q\nmeasured 0.52 N\n".to_string())];
    assert_eq!(restated_figure_problems(readme, &pages).len(), 1);
    let history = [("docs/history.md".to_string(), "was 0.52 N\n".to_string())];
    assert!(restated_figure_problems(readme, &history).is_empty());
    assert!(readme_prose_problems(readme).is_empty());
    let restated = readme.replace("x\n", "M was 0.52 N\n");
    assert_eq!(readme_prose_problems(&restated).len(), 1);
}
