//! CLIP's byte-level BPE tokenizer (the text side of `gs4city features`), written from the
//! description of OpenAI CLIP's `simple_tokenizer` (and HF's `CLIPTokenizer`, which produces the
//! same ids):
//!
//! 1. clean: NFC, every run of whitespace to one space, trimmed, lowercased (ftfy's mojibake
//!    repair and HTML unescaping are not done: prompts are plain text);
//! 2. pre-tokenise with `<|startoftext|>|<|endoftext|>|'s|'t|'re|'ve|'m|'ll|'d|\p{L}+|\p{N}|[^\s\p{L}\p{N}]+`;
//! 3. each piece's UTF-8 bytes to GPT-2's printable byte characters, `</w>` on the last one,
//!    then the merges applied lowest rank first until none applies;
//! 4. `<|startoftext|>` + ids + `<|endoftext|>`, cut to the context length (the last id then
//!    `<|endoftext|>`) and padded with 0.
//!
//! The vocabulary comes from `vocab.json` + `merges.txt` (HF's and open_clip's hub layout) or
//! from OpenAI's `bpe_simple_vocab_16e6.txt` (merges only; the vocabulary is then the 256 byte
//! characters, the same with `</w>`, every merge, and the two special tokens, in that order).
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use regex::Regex;
use unicode_normalization::UnicodeNormalization;

/// CLIP's context length.
pub const CONTEXT: usize = 77;
const SOT: &str = "<|startoftext|>";
const EOT: &str = "<|endoftext|>";
/// Merges OpenAI's tokenizer reads from `bpe_simple_vocab_16e6.txt` (49152 − 256 − 2).
const OPENAI_MERGES: usize = 49152 - 256 - 2;

/// A tokenizer file that cannot be used; names the file and, where one is at fault, the line.
#[derive(Debug, thiserror::Error)]
#[error("tokenizer file {path}: {why}")]
pub struct BpeError {
    pub path: PathBuf,
    pub why: String,
}

/// CLIP's tokenizer: byte characters, merge ranks, vocabulary.
#[derive(Debug, Clone)]
pub struct Bpe {
    byte_char: [char; 256],
    ranks: HashMap<(String, String), usize>,
    vocab: HashMap<String, u32>,
    sot: u32,
    eot: u32,
    pattern: Regex,
}

/// GPT-2's byte → printable character table (`bytes_to_unicode`): the printable Latin-1 bytes
/// stand for themselves, the others for 256, 257, … in byte order.
fn byte_chars() -> [char; 256] {
    let printable = |b: u32| (0x21..=0x7e).contains(&b) || (0xa1..=0xac).contains(&b) || b >= 0xae;
    let mut out = ['\0'; 256];
    let mut n = 0u32;
    for (b, c) in out.iter_mut().enumerate() {
        let b = b as u32;
        *c = if printable(b) {
            char::from_u32(b).expect("Latin-1")
        } else {
            n += 1;
            char::from_u32(255 + n).expect("below the surrogates")
        };
    }
    out
}

/// The byte characters in the order of CLIP's vocabulary (printable ones first).
fn vocab_order(chars: &[char; 256]) -> Vec<char> {
    let mut v: Vec<char> = chars.to_vec();
    v.sort_by_key(|&c| c as u32);
    v
}

fn parse_merges(path: &Path, text: &str, limit: usize) -> Result<Vec<(String, String)>, BpeError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if out.len() == limit {
            break;
        }
        if (i == 0 && line.contains("#version")) || line.trim().is_empty() {
            continue;
        }
        let mut parts = line.split(' ');
        match (parts.next(), parts.next(), parts.next()) {
            (Some(a), Some(b), None) if !a.is_empty() && !b.is_empty() => {
                out.push((a.to_string(), b.to_string()))
            }
            _ => {
                return Err(BpeError {
                    path: path.to_path_buf(),
                    why: format!("line {}: not a merge (two symbols and one space)", i + 1),
                });
            }
        }
    }
    Ok(out)
}

fn read_text(path: &Path) -> Result<String, BpeError> {
    std::fs::read_to_string(path).map_err(|e| BpeError {
        path: path.to_path_buf(),
        why: e.to_string(),
    })
}

impl Bpe {
    /// From HF's / open_clip's `vocab.json` (token → id) and `merges.txt`.
    pub fn from_vocab_merges(vocab_path: &Path, merges_path: &Path) -> Result<Bpe, BpeError> {
        let vocab: HashMap<String, u32> =
            serde_json::from_str(&read_text(vocab_path)?).map_err(|e| BpeError {
                path: vocab_path.to_path_buf(),
                why: format!("not a JSON object of token → id: {e}"),
            })?;
        let merges = parse_merges(merges_path, &read_text(merges_path)?, usize::MAX)?;
        Bpe::new(vocab, merges, vocab_path, merges_path)
    }

    /// From OpenAI's `bpe_simple_vocab_16e6.txt` (uncompressed): its first 48894 merges.
    pub fn from_openai_merges(path: &Path) -> Result<Bpe, BpeError> {
        let merges = parse_merges(path, &read_text(path)?, OPENAI_MERGES)?;
        let chars = vocab_order(&byte_chars());
        let mut tokens: Vec<String> = chars.iter().map(|c| c.to_string()).collect();
        tokens.extend(chars.iter().map(|c| format!("{c}</w>")));
        tokens.extend(merges.iter().map(|(a, b)| format!("{a}{b}")));
        tokens.push(SOT.into());
        tokens.push(EOT.into());
        let vocab = tokens
            .into_iter()
            .enumerate()
            .map(|(i, t)| (t, i as u32))
            .collect();
        Bpe::new(vocab, merges, path, path)
    }

    fn new(
        vocab: HashMap<String, u32>,
        merges: Vec<(String, String)>,
        vocab_path: &Path,
        merges_path: &Path,
    ) -> Result<Bpe, BpeError> {
        let byte_char = byte_chars();
        let missing = |t: &str, path: &Path, why: String| BpeError {
            path: path.to_path_buf(),
            why: format!("the vocabulary has no token {t:?} ({why})"),
        };
        for c in byte_char {
            for t in [c.to_string(), format!("{c}</w>")] {
                if !vocab.contains_key(&t) {
                    return Err(missing(&t, vocab_path, "a byte character".into()));
                }
            }
        }
        let special = |t: &str| {
            vocab
                .get(t)
                .copied()
                .ok_or_else(|| missing(t, vocab_path, "a special token".into()))
        };
        let (sot, eot) = (special(SOT)?, special(EOT)?);
        let mut ranks = HashMap::with_capacity(merges.len());
        for (rank, (a, b)) in merges.into_iter().enumerate() {
            let joined = format!("{a}{b}");
            if !vocab.contains_key(&joined) {
                return Err(missing(
                    &joined,
                    merges_path,
                    format!("merge {} of {}", rank + 1, merges_path.display()),
                ));
            }
            ranks.entry((a, b)).or_insert(rank);
        }
        let pattern = Regex::new(
            r"(?i)<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|\p{L}+|\p{N}|[^\s\p{L}\p{N}]+",
        )
        .expect("a valid pattern");
        Ok(Bpe {
            byte_char,
            ranks,
            vocab,
            sot,
            eot,
            pattern,
        })
    }

    /// The vocabulary's size (largest id + 1).
    pub fn vocab_size(&self) -> usize {
        self.vocab.values().max().map_or(0, |&m| m as usize + 1)
    }

    /// The merged symbols of one pre-tokenised piece (already in byte characters).
    fn merge(&self, piece: &str) -> Vec<String> {
        let chars: Vec<char> = piece.chars().collect();
        let mut word: Vec<String> = chars.iter().map(|c| c.to_string()).collect();
        if let Some(last) = word.last_mut() {
            last.push_str("</w>");
        }
        while word.len() > 1 {
            let best = word
                .windows(2)
                .filter_map(|p| {
                    self.ranks
                        .get(&(p[0].clone(), p[1].clone()))
                        .map(|&r| (r, p[0].clone(), p[1].clone()))
                })
                .min_by_key(|(r, _, _)| *r);
            let Some((_, a, b)) = best else { break };
            let mut next = Vec::with_capacity(word.len());
            let mut i = 0;
            while i < word.len() {
                if i + 1 < word.len() && word[i] == a && word[i + 1] == b {
                    next.push(format!("{a}{b}"));
                    i += 2;
                } else {
                    next.push(std::mem::take(&mut word[i]));
                    i += 1;
                }
            }
            word = next;
        }
        word
    }

    /// The ids of `text` without the special tokens around it.
    pub fn encode(&self, text: &str) -> Vec<u32> {
        let nfc: String = text.nfc().collect();
        let clean = nfc.split_whitespace().collect::<Vec<_>>().join(" ");
        let lower = clean.to_lowercase();
        let mut ids = Vec::new();
        for m in self.pattern.find_iter(&lower) {
            let piece = m.as_str();
            if piece == SOT || piece == EOT {
                ids.push(if piece == SOT { self.sot } else { self.eot });
                continue;
            }
            let bytes: String = piece.bytes().map(|b| self.byte_char[b as usize]).collect();
            for sym in self.merge(&bytes) {
                ids.push(self.vocab[&sym]);
            }
        }
        ids
    }

    /// CLIP's model input: `<|startoftext|>`, the ids, `<|endoftext|>`, cut to `context` (the
    /// last id then `<|endoftext|>`), padded with 0.
    pub fn tokenize(&self, text: &str, context: usize) -> Vec<i64> {
        let mut ids: Vec<i64> = std::iter::once(self.sot)
            .chain(self.encode(text))
            .chain(std::iter::once(self.eot))
            .map(i64::from)
            .collect();
        if ids.len() > context {
            ids.truncate(context);
            if let Some(last) = ids.last_mut() {
                *last = i64::from(self.eot);
            }
        }
        ids.resize(context, 0);
        ids
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_table_is_gpt2s() {
        let t = byte_chars();
        assert_eq!(t[b'a' as usize], 'a');
        assert_eq!(t[b'!' as usize], '!');
        // space is byte 32, the 33rd non-printable byte in order (0..=32) → 256 + 32
        assert_eq!(t[b' ' as usize] as u32, 256 + 32);
        assert_eq!(t[0] as u32, 256);
        assert_eq!(t[0xad] as u32, 256 + 32 + 1 + 34);
        let mut all: Vec<u32> = t.iter().map(|&c| c as u32).collect();
        all.sort_unstable();
        all.dedup();
        assert_eq!(all.len(), 256);
    }
}
