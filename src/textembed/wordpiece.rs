//! BERT's uncased tokenizer from `vocab.txt`: basic tokenization (clean, split CJK ideographs,
//! lowercase, strip accents, split whitespace and punctuation), then greedy longest-match-first
//! WordPiece with `##` continuations, wrapped in `[CLS]` … `[SEP]`. The rules of BERT's
//! `BasicTokenizer` + `WordpieceTokenizer` (uncased, `tokenize_chinese_chars`), written from
//! their description; `tests/textembed.rs` checks the ids against the Python model's tokenizer.
use std::collections::HashMap;
use std::path::Path;

use unicode_normalization::UnicodeNormalization;
use unicode_normalization::char::is_combining_mark;

use super::EmbedError;

/// Words longer than this (in characters) become `[UNK]`, as in BERT.
const MAX_WORD_CHARS: usize = 100;

/// A WordPiece vocabulary and its special tokens.
#[derive(Debug, Clone)]
pub struct WordPiece {
    ids: HashMap<String, u32>,
    cls: u32,
    sep: u32,
    unk: u32,
}

/// CJK ideographs (the blocks BERT surrounds with spaces).
fn is_cjk(c: char) -> bool {
    matches!(c as u32,
        0x4E00..=0x9FFF | 0x3400..=0x4DBF | 0x20000..=0x2A6DF | 0x2A700..=0x2B73F
        | 0x2B740..=0x2B81F | 0x2B820..=0x2CEAF | 0xF900..=0xFAFF | 0x2F800..=0x2FA1F)
}

/// BERT's punctuation: every non-alphanumeric ASCII printable character, and the Unicode
/// punctuation blocks (Latin-1 punctuation, General Punctuation, CJK Symbols and Punctuation,
/// the fullwidth ASCII punctuation); an approximation of the Unicode `P*` categories that
/// covers what a query is written with.
fn is_punct(c: char) -> bool {
    c.is_ascii_punctuation()
        || matches!(c as u32,
            0xA1 | 0xA7 | 0xAB | 0xB6 | 0xB7 | 0xBB | 0xBF | 0x2010..=0x2027 | 0x2030..=0x205E
            | 0x3001..=0x3003 | 0x3008..=0x3011 | 0x3014..=0x301F | 0xFF01..=0xFF0F
            | 0xFF1A..=0xFF20 | 0xFF3B..=0xFF40 | 0xFF5B..=0xFF65)
}

impl WordPiece {
    /// Reads `vocab.txt` (one token per line, id = line number).
    pub fn read(path: &Path) -> Result<WordPiece, EmbedError> {
        let text = std::fs::read_to_string(path).map_err(|e| EmbedError::Model {
            path: path.to_path_buf(),
            why: e.to_string(),
        })?;
        WordPiece::from_lines(text.lines()).map_err(|why| EmbedError::Model {
            path: path.to_path_buf(),
            why,
        })
    }

    /// From the vocabulary's lines (id = line number).
    pub fn from_lines<'a>(lines: impl Iterator<Item = &'a str>) -> Result<WordPiece, String> {
        let mut ids = HashMap::new();
        for (i, l) in lines.enumerate() {
            ids.entry(l.trim_end_matches('\r').to_string())
                .or_insert(i as u32);
        }
        let special = |t: &str| {
            ids.get(t)
                .copied()
                .ok_or_else(|| format!("the vocabulary has no {t} token"))
        };
        Ok(WordPiece {
            cls: special("[CLS]")?,
            sep: special("[SEP]")?,
            unk: special("[UNK]")?,
            ids,
        })
    }

    /// The basic tokens of `text` (lowercased, accents stripped, punctuation split off).
    pub fn basic(text: &str) -> Vec<String> {
        let mut spaced = String::with_capacity(text.len());
        for c in text.chars() {
            if c == '\0' || c == '\u{FFFD}' || (c.is_control() && !c.is_whitespace()) {
                continue;
            }
            if c.is_whitespace() {
                spaced.push(' ');
            } else if is_cjk(c) {
                spaced.extend([' ', c, ' ']);
            } else {
                spaced.push(c);
            }
        }
        let mut out = Vec::new();
        for word in spaced.split(' ').filter(|w| !w.is_empty()) {
            let clean: String = word
                .to_lowercase()
                .nfd()
                .filter(|&c| !is_combining_mark(c))
                .collect();
            let mut cur = String::new();
            for c in clean.chars() {
                if is_punct(c) {
                    if !cur.is_empty() {
                        out.push(std::mem::take(&mut cur));
                    }
                    out.push(c.to_string());
                } else {
                    cur.push(c);
                }
            }
            if !cur.is_empty() {
                out.push(cur);
            }
        }
        out
    }

    /// The WordPiece ids of one basic token: greedy longest match first, continuations
    /// prefixed `##`; a word that cannot be covered (or is too long) is `[UNK]`.
    fn word(&self, word: &str, out: &mut Vec<u32>) {
        let chars: Vec<char> = word.chars().collect();
        if chars.len() > MAX_WORD_CHARS {
            out.push(self.unk);
            return;
        }
        let start_len = out.len();
        let mut start = 0;
        while start < chars.len() {
            let mut end = chars.len();
            let mut found = None;
            while end > start {
                let piece: String = chars[start..end].iter().collect();
                let key = if start > 0 {
                    format!("##{piece}")
                } else {
                    piece
                };
                if let Some(&id) = self.ids.get(&key) {
                    found = Some(id);
                    break;
                }
                end -= 1;
            }
            let Some(id) = found else {
                out.truncate(start_len);
                out.push(self.unk);
                return;
            };
            out.push(id);
            start = end;
        }
    }

    /// `[CLS]` + the WordPiece ids of `text` + `[SEP]`, at most `max_len` ids in all (longer
    /// texts are truncated before `[SEP]`, as sentence-transformers does).
    pub fn encode(&self, text: &str, max_len: usize) -> Vec<u32> {
        let mut ids = vec![self.cls];
        for w in WordPiece::basic(text) {
            self.word(&w, &mut ids);
        }
        ids.truncate(max_len.max(2) - 1);
        ids.push(self.sep);
        ids
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basic_tokens_lowercase_strip_accents_and_split_punctuation() {
        assert_eq!(
            WordPiece::basic("  Café, the ROOF!\tof\u{7}“x”  "),
            ["cafe", ",", "the", "roof", "!", "of", "“", "x", "”"]
        );
        assert_eq!(WordPiece::basic("a窓b"), ["a", "窓", "b"]);
    }

    #[test]
    fn wordpiece_takes_the_longest_match_first() {
        let v = WordPiece::from_lines(
            [
                "[PAD]", "[UNK]", "[CLS]", "[SEP]", "un", "##aff", "##able", "want", "##ed", ",",
            ]
            .into_iter(),
        )
        .unwrap();
        assert_eq!(v.encode("unaffable, wanted", 64), [2, 4, 5, 6, 9, 7, 8, 3]);
        // A word that cannot be covered is one [UNK]; truncation keeps [SEP].
        assert_eq!(v.encode("wantx want", 64), [2, 1, 7, 3]);
        assert_eq!(v.encode("want want want", 3), [2, 7, 3]);
        assert!(WordPiece::from_lines(["a"].into_iter()).is_err());
    }
}
