//! Integration tests live in `tests/tests/`; they start the real binaries.
