//! Input quoted in error messages, made safe to print: a message that
//! quotes a line of a file must not carry the file's control bytes (a
//! terminal escape sequence would recolour or rewrite the user's terminal).

use std::borrow::Cow;

/// `text` with every control character (C0, DEL, C1) and every Unicode
/// bidirectional override escaped as Rust writes it (`\u{1b}`, `\t`);
/// everything else, the backslash included, as it is.
pub fn escape_controls(text: &str) -> Cow<'_, str> {
    let unsafe_char =
        |c: char| c.is_control() || matches!(c, '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}');
    if !text.chars().any(unsafe_char) {
        return Cow::Borrowed(text);
    }
    let mut out = String::with_capacity(text.len() + 8);
    for c in text.chars() {
        if unsafe_char(c) {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    Cow::Owned(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_characters_are_escaped() {
        assert_eq!(escape_controls("plain `1.5` \\ é"), "plain `1.5` \\ é");
        assert_eq!(escape_controls("1\x1b[31mX"), "1\\u{1b}[31mX");
        assert_eq!(
            escape_controls("a\tb\rc\u{7f}\u{9b}"),
            "a\\tb\\rc\\u{7f}\\u{9b}"
        );
        assert_eq!(escape_controls("x\u{202e}y"), "x\\u{202e}y");
    }
}
