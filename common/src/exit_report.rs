//! How the binaries print the error that ends them. A user who has
//! `RUST_BACKTRACE=1` set (for panics) should still see a short message for a
//! missing file or a bad key, not a stack trace. So the message comes first,
//! then each cause that adds something: a library error whose message already
//! quotes its source is not repeated. `RUST_LIB_BACKTRACE=1` asks for the
//! backtrace of errors explicitly.

use std::error::Error;
use std::fmt::{Debug, Write as _};
use std::ops::Deref;
use std::process::ExitCode;

/// `error: <message>`, then one `  caused by: <cause>` line per cause whose
/// text the line before does not already contain.
pub fn render_error_chain(err: &(dyn Error + 'static)) -> String {
    let mut out = format!("error: {err}");
    let mut last = err.to_string();
    let mut cause = err.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !text.is_empty() && !last.contains(&text) {
            let _ = write!(out, "\n  caused by: {text}");
        }
        last = text;
        cause = c.source();
    }
    out
}

/// The exit code of a binary's `main` for `result`: success, or failure after
/// printing the error on stderr ([`render_error_chain`]; with
/// `RUST_LIB_BACKTRACE=1`, the error's own debug form with its backtrace).
pub fn exit_code<E>(result: Result<(), E>) -> ExitCode
where
    E: Deref<Target = dyn Error + Send + Sync + 'static> + Debug,
{
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            if std::env::var_os("RUST_LIB_BACKTRACE").is_some_and(|v| v == "1") {
                eprintln!("error: {e:?}");
            } else {
                let err: &(dyn Error + 'static) = &*e;
                eprintln!("{}", render_error_chain(err));
            }
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    enum Inner {
        #[error("no such file")]
        Missing,
    }

    #[derive(Debug, thiserror::Error)]
    enum Outer {
        /// Quotes its source: the chain must not repeat it.
        #[error("cannot read scenario a.yaml: {0}")]
        Quoting(#[source] Inner),
        /// Does not quote it: the cause is shown.
        #[error("cannot load the fleet")]
        Plain(#[source] Inner),
    }

    #[test]
    fn a_cause_already_in_the_message_is_not_repeated() {
        let e = Outer::Quoting(Inner::Missing);
        assert_eq!(
            render_error_chain(&e),
            "error: cannot read scenario a.yaml: no such file"
        );
    }

    #[test]
    fn a_cause_the_message_does_not_quote_gets_its_line() {
        let e = Outer::Plain(Inner::Missing);
        assert_eq!(
            render_error_chain(&e),
            "error: cannot load the fleet\n  caused by: no such file"
        );
    }
}
