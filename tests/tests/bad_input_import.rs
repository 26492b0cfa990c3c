//! Every broken input of the corpus is rejected with a precise error, and never panics.

use std::collections::HashSet;
use std::panic::{AssertUnwindSafe, catch_unwind};

use arbor_server::import::{ImportOptions, import_file};
use arbor_tests::corpus::bad_inputs;

#[test]
fn bad_inputs_are_rejected_with_clear_errors() {
    let cases = bad_inputs();
    assert!(cases.len() >= 24, "only {} corpus cases", cases.len());
    let names: HashSet<_> = cases.iter().map(|c| c.name).collect();
    assert_eq!(names.len(), cases.len(), "corpus case names must be unique");

    let mut failures = Vec::new();
    for case in &cases {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(&case.file_name);
        std::fs::write(&path, &case.bytes).expect("writing the case");
        let scratch = dir.path().join("scratch");
        std::fs::create_dir(&scratch).expect("scratch dir");
        let opts = ImportOptions {
            format: None,
            raw: case.raw,
            ..ImportOptions::default()
        };
        let result = catch_unwind(AssertUnwindSafe(|| import_file(&path, &opts, &scratch)));
        match result {
            Err(_) => failures.push(format!("{}: PANICKED", case.name)),
            Ok(Ok(source)) => failures.push(format!(
                "{}: accepted ({}), expected an error containing {:?}",
                case.name,
                source.describe(),
                case.expect
            )),
            Ok(Err(e)) => {
                let msg = e.to_string();
                println!("{:<36} {msg}", case.name);
                if !msg.to_lowercase().contains(&case.expect.to_lowercase()) {
                    failures.push(format!(
                        "{}: message {msg:?} does not contain {:?}",
                        case.name, case.expect
                    ));
                }
                if !msg.contains(&case.file_name) {
                    failures.push(format!(
                        "{}: message {msg:?} does not name the file",
                        case.name
                    ));
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
