//! The selection grammar of `gs4city query --where EXPR` (docs/query.md):
//!
//! ```text
//! expr    := and ("or" and)*
//! and     := unary ("and" unary)*
//! unary   := "not" unary | "(" expr ")" | term
//! term    := "class" op NAME | "level" op LEVEL | "id" op VALUE | "category" op NAME
//!          | "label" op INT | "within" "(" VALUE ")" | "text" "(" VALUE ")"
//!          | "attr" "(" VALUE ")" cmp VALUE [UNIT] | NAME cmp VALUE [UNIT]
//! op      := "=" | "!="                     cmp := "=" | "!=" | "<" | "<=" | ">" | ">="
//! VALUE   := a number, a "double" or 'single' quoted string, or a bare word
//! ```
//! Keywords (`and or not class level id category label within text attr`) are case-insensitive;
//! an attribute that is named like a keyword is written `attr("class")`. A number may carry a
//! unit, attached (`10m`) or as the next word (`10 m`), e.g. `measuredHeight > 1200 cm`.
//!
//! Every error is one line that names the column (1-based, in characters) where the problem is.
use std::fmt;

/// A parse error: the 1-based column (in characters) and what is wrong there.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("column {column}: {why}")]
pub struct ParseError {
    pub column: usize,
    pub why: String,
}

/// A comparison operator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Op {
    #[serde(rename = "=")]
    Eq,
    #[serde(rename = "!=")]
    Ne,
    #[serde(rename = "<")]
    Lt,
    #[serde(rename = "<=")]
    Le,
    #[serde(rename = ">")]
    Gt,
    #[serde(rename = ">=")]
    Ge,
}

impl Op {
    pub fn as_str(self) -> &'static str {
        match self {
            Op::Eq => "=",
            Op::Ne => "!=",
            Op::Lt => "<",
            Op::Le => "<=",
            Op::Gt => ">",
            Op::Ge => ">=",
        }
    }

    /// Whether `ordering` (attribute value compared with the literal) satisfies the operator.
    pub fn holds(self, ordering: std::cmp::Ordering) -> bool {
        use std::cmp::Ordering::*;
        match self {
            Op::Eq => ordering == Equal,
            Op::Ne => ordering != Equal,
            Op::Lt => ordering == Less,
            Op::Le => ordering != Greater,
            Op::Gt => ordering == Greater,
            Op::Ge => ordering != Less,
        }
    }
}

/// A literal on the right of a comparison.
#[derive(Debug, Clone, PartialEq)]
pub enum Literal {
    /// A number as written (`text`), its value, and the unit written after it (if any).
    Number {
        value: f64,
        text: String,
        unit: Option<String>,
    },
    /// A quoted string or a bare word that is not a number.
    Text(String),
}

impl fmt::Display for Literal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Literal::Number {
                text, unit: None, ..
            } => write!(f, "{text}"),
            Literal::Number {
                text,
                unit: Some(u),
                ..
            } => write!(f, "{text} {u}"),
            Literal::Text(s) => write!(f, "{}", quote(s)),
        }
    }
}

/// One term of the grammar; `column` is where the term starts (for validation errors).
#[derive(Debug, Clone, PartialEq)]
pub enum Term {
    /// A CityGML class with its descendants (`class=Building` selects its surfaces and openings).
    Class { name: String, column: usize },
    /// A hierarchy level (`feature`, `surface`, `part`), of the entity itself.
    Level { name: String, column: usize },
    /// One entity by gml:id (without its descendants).
    Id { id: String, column: usize },
    /// An entity and all its descendants.
    Within { id: String, column: usize },
    /// An evaluation class of the label table (`wall … car`, `docs/design.md` class ids).
    Category { name: String, column: usize },
    /// A label id of the fused label table.
    Label { id: i64, column: usize },
    /// A text prompt of `features/prompts.json`, matched against the per-label features.
    Text { prompt: String, column: usize },
    /// An attribute comparison (attributes are inherited from the nearest ancestor).
    Attr {
        name: String,
        op: Op,
        value: Literal,
        column: usize,
    },
}

/// A parsed selection.
#[derive(Debug, Clone, PartialEq)]
pub enum Expr {
    And(Box<Expr>, Box<Expr>),
    Or(Box<Expr>, Box<Expr>),
    Not(Box<Expr>),
    Term(Term),
    /// A query vector given as a file (`--text-feature F.npy`): not written in the grammar.
    TextFeature {
        path: String,
        vector: Vec<f32>,
    },
}

impl Expr {
    /// `a and b`.
    pub fn and(a: Expr, b: Expr) -> Expr {
        Expr::And(Box::new(a), Box::new(b))
    }

    /// Every term, left to right.
    pub fn terms(&self) -> Vec<&Term> {
        let mut out = Vec::new();
        fn walk<'a>(e: &'a Expr, out: &mut Vec<&'a Term>) {
            match e {
                Expr::And(a, b) | Expr::Or(a, b) => {
                    walk(a, out);
                    walk(b, out);
                }
                Expr::Not(a) => walk(a, out),
                Expr::Term(t) => out.push(t),
                Expr::TextFeature { .. } => {}
            }
        }
        walk(self, &mut out);
        out
    }
}

fn quote(s: &str) -> String {
    format!("\"{}\"", s.replace('\\', "\\\\").replace('"', "\\\""))
}

fn is_plain_word(s: &str) -> bool {
    !s.is_empty()
        && s.chars().all(is_word_char)
        && s.chars()
            .next()
            .is_some_and(|c| !c.is_ascii_digit() && c != '-' && c != '+')
        && !KEYWORDS.contains(&s.to_ascii_lowercase().as_str())
}

impl fmt::Display for Expr {
    /// The canonical text of the selection (fully parenthesised where it matters); parsing it
    /// again gives the same tree.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let word = |s: &str| {
            if is_plain_word(s) {
                s.to_string()
            } else {
                quote(s)
            }
        };
        match self {
            Expr::And(a, b) => write!(f, "({a} and {b})"),
            Expr::Or(a, b) => write!(f, "({a} or {b})"),
            Expr::Not(a) => write!(f, "not {a}"),
            Expr::TextFeature { path, .. } => write!(f, "text-feature({})", quote(path)),
            Expr::Term(t) => match t {
                Term::Class { name, .. } => write!(f, "class={}", word(name)),
                Term::Level { name, .. } => write!(f, "level={}", word(name)),
                Term::Id { id, .. } => write!(f, "id={}", quote(id)),
                Term::Within { id, .. } => write!(f, "within({})", quote(id)),
                Term::Category { name, .. } => write!(f, "category={}", word(name)),
                Term::Label { id, .. } => write!(f, "label={id}"),
                Term::Text { prompt, .. } => write!(f, "text({})", quote(prompt)),
                Term::Attr {
                    name, op, value, ..
                } => {
                    if is_plain_word(name) {
                        write!(f, "{name}{}{value}", op.as_str())
                    } else {
                        write!(f, "attr({}){}{value}", quote(name), op.as_str())
                    }
                }
            },
        }
    }
}

const KEYWORDS: [&str; 10] = [
    "and", "or", "not", "class", "level", "id", "category", "label", "within", "text",
];

/// Characters of a bare word (names, gml:ids, dates, attribute names such as
/// `@cityeditor:layer` or `measuredHeight.uom`).
fn is_word_char(c: char) -> bool {
    c.is_alphanumeric() || matches!(c, '_' | '.' | ':' | '@' | '-' | '+' | '#' | '/' | '²' | '³')
}

#[derive(Debug, Clone, PartialEq)]
enum Tok {
    Word(String),
    Str(String),
    Op(Op),
    LParen,
    RParen,
    End,
}

impl Tok {
    fn describe(&self) -> String {
        match self {
            Tok::Word(w) => format!("`{w}`"),
            Tok::Str(s) => format!("the string {}", quote(s)),
            Tok::Op(o) => format!("`{}`", o.as_str()),
            Tok::LParen => "`(`".into(),
            Tok::RParen => "`)`".into(),
            Tok::End => "the end".into(),
        }
    }
}

/// Splits the text into tokens with their 1-based character columns.
fn lex(text: &str) -> Result<Vec<(Tok, usize)>, ParseError> {
    let chars: Vec<char> = text.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        let col = i + 1;
        if c.is_whitespace() {
            i += 1;
            continue;
        }
        match c {
            '(' => {
                out.push((Tok::LParen, col));
                i += 1;
            }
            ')' => {
                out.push((Tok::RParen, col));
                i += 1;
            }
            '=' => {
                // `==` is accepted as `=`.
                i += if chars.get(i + 1) == Some(&'=') { 2 } else { 1 };
                out.push((Tok::Op(Op::Eq), col));
            }
            '!' | '<' | '>' => {
                let eq = chars.get(i + 1) == Some(&'=');
                let op = match (c, eq) {
                    ('!', true) => Op::Ne,
                    ('<', true) => Op::Le,
                    ('>', true) => Op::Ge,
                    ('<', false) if chars.get(i + 1) == Some(&'>') => {
                        i += 1; // `<>` is `!=`
                        Op::Ne
                    }
                    ('<', false) => Op::Lt,
                    ('>', false) => Op::Gt,
                    _ => {
                        return Err(ParseError {
                            column: col,
                            why: "`!` must be followed by `=` (write `not` for negation)".into(),
                        });
                    }
                };
                i += if eq { 2 } else { 1 };
                out.push((Tok::Op(op), col));
            }
            '"' | '\'' => {
                let mut s = String::new();
                let mut j = i + 1;
                loop {
                    match chars.get(j) {
                        None => {
                            return Err(ParseError {
                                column: col,
                                why: format!("unterminated string (no closing {c})"),
                            });
                        }
                        Some('\\') if matches!(chars.get(j + 1), Some(&q) if q == c || q == '\\') =>
                        {
                            s.push(chars[j + 1]);
                            j += 2;
                        }
                        Some(&q) if q == c => break,
                        Some(&x) => {
                            s.push(x);
                            j += 1;
                        }
                    }
                }
                out.push((Tok::Str(s), col));
                i = j + 1;
            }
            c if is_word_char(c) => {
                let mut j = i;
                while j < chars.len() && is_word_char(chars[j]) {
                    j += 1;
                }
                out.push((Tok::Word(chars[i..j].iter().collect()), col));
                i = j;
            }
            c => {
                return Err(ParseError {
                    column: col,
                    why: format!("unexpected character `{c}`"),
                });
            }
        }
    }
    out.push((Tok::End, chars.len() + 1));
    Ok(out)
}

struct Parser {
    toks: Vec<(Tok, usize)>,
    pos: usize,
    /// Open `(` and `not` around the current position.
    depth: usize,
    /// Terms read so far.
    terms: usize,
}

/// The deepest nesting of `(` and `not` an expression may have: the parser and every walk of
/// the expression recurse once per level, on a thread's stack (the viewer's too).
pub const MAX_NESTING: usize = 128;
/// The most terms an expression may have (a chain of `and`/`or` is as deep as it is long).
pub const MAX_TERMS: usize = 4096;

/// A number at the start of `w` and the rest (a unit), e.g. `10m` → (10, "m"), `1e3` → (1000, "").
fn split_number(w: &str) -> Option<(f64, &str)> {
    // The longest prefix that parses as a finite f64.
    let mut best = None;
    for (i, _) in w
        .char_indices()
        .skip(1)
        .chain(std::iter::once((w.len(), ' ')))
    {
        if let Ok(v) = w[..i].parse::<f64>()
            && v.is_finite()
            && !w[..i].ends_with(['e', 'E'])
        {
            best = Some((v, &w[i..]));
        }
    }
    best
}

fn is_keyword(w: &str, k: &str) -> bool {
    w.eq_ignore_ascii_case(k)
}

impl Parser {
    fn peek(&self) -> &(Tok, usize) {
        &self.toks[self.pos]
    }

    fn next(&mut self) -> (Tok, usize) {
        let t = self.toks[self.pos].clone();
        if self.pos + 1 < self.toks.len() {
            self.pos += 1;
        }
        t
    }

    fn err<T>(&self, column: usize, why: impl Into<String>) -> Result<T, ParseError> {
        Err(ParseError {
            column,
            why: why.into(),
        })
    }

    fn peek_keyword(&self, k: &str) -> bool {
        matches!(&self.peek().0, Tok::Word(w) if is_keyword(w, k))
    }

    fn expr(&mut self) -> Result<Expr, ParseError> {
        let mut left = self.and()?;
        while self.peek_keyword("or") {
            self.next();
            let right = self.and()?;
            left = Expr::Or(Box::new(left), Box::new(right));
        }
        Ok(left)
    }

    fn and(&mut self) -> Result<Expr, ParseError> {
        let mut left = self.unary()?;
        while self.peek_keyword("and") {
            self.next();
            let right = self.unary()?;
            left = Expr::And(Box::new(left), Box::new(right));
        }
        Ok(left)
    }

    fn unary(&mut self) -> Result<Expr, ParseError> {
        if self.peek_keyword("not") || self.peek().0 == Tok::LParen {
            self.depth += 1;
            if self.depth > MAX_NESTING {
                let c = self.peek().1;
                return self.err(
                    c,
                    format!("nested deeper than {MAX_NESTING} levels of `(` and `not`"),
                );
            }
            let e = self.nested();
            self.depth -= 1;
            return e;
        }
        self.term()
    }

    /// `not` UNARY or `(` EXPR `)`.
    fn nested(&mut self) -> Result<Expr, ParseError> {
        if self.peek_keyword("not") {
            self.next();
            return Ok(Expr::Not(Box::new(self.unary()?)));
        }
        let (_, col) = self.next();
        let e = self.expr()?;
        let (t, c) = self.next();
        if t != Tok::RParen {
            return self.err(
                c,
                format!(
                    "expected `)` to close the `(` of column {col}, found {}",
                    t.describe()
                ),
            );
        }
        Ok(e)
    }

    /// `(` VALUE `)` after a function word.
    fn call_arg(&mut self, name: &str) -> Result<String, ParseError> {
        let (t, c) = self.next();
        if t != Tok::LParen {
            return self.err(
                c,
                format!("expected `(` after `{name}`, found {}", t.describe()),
            );
        }
        let (t, c) = self.next();
        let arg = match t {
            Tok::Word(w) => w,
            Tok::Str(s) => s,
            t => {
                return self.err(
                    c,
                    format!(
                        "expected a value inside `{name}(…)`, found {}",
                        t.describe()
                    ),
                );
            }
        };
        let (t, c) = self.next();
        if t != Tok::RParen {
            return self.err(
                c,
                format!(
                    "expected `)` after the value of `{name}(…)`, found {}",
                    t.describe()
                ),
            );
        }
        Ok(arg)
    }

    /// `=` or `!=` after a keyword term; returns whether it was `!=`.
    fn eq_op(&mut self, name: &str) -> Result<bool, ParseError> {
        let (t, c) = self.next();
        match t {
            Tok::Op(Op::Eq) => Ok(false),
            Tok::Op(Op::Ne) => Ok(true),
            Tok::Op(o) => self.err(
                c,
                format!(
                    "`{name}` compares with `=` or `!=` only, not `{}`",
                    o.as_str()
                ),
            ),
            t => self.err(
                c,
                format!(
                    "expected `=` or `!=` after `{name}`, found {}",
                    t.describe()
                ),
            ),
        }
    }

    fn value(&mut self, after: &str) -> Result<(String, usize), ParseError> {
        let (t, c) = self.next();
        match t {
            Tok::Word(w) => Ok((w, c)),
            Tok::Str(s) => Ok((s, c)),
            t => self.err(
                c,
                format!("expected a value after {after}, found {}", t.describe()),
            ),
        }
    }

    fn term(&mut self) -> Result<Expr, ParseError> {
        let (t, col) = self.next();
        self.terms += 1;
        if self.terms > MAX_TERMS {
            return self.err(col, format!("more than {MAX_TERMS} terms"));
        }
        let word = match t {
            Tok::Word(w) => w,
            t => {
                return self.err(
                    col,
                    format!(
                        "expected a term (class=…, level=…, id=…, within(…), category=…, label=…, text(…) or an attribute comparison), found {}",
                        t.describe()
                    ),
                );
            }
        };
        let lower = word.to_ascii_lowercase();
        let term = match lower.as_str() {
            "and" | "or" => return self.err(col, format!("`{word}` needs a term on its left")),
            "within" => Term::Within {
                id: self.call_arg("within")?,
                column: col,
            },
            "text" => Term::Text {
                prompt: self.call_arg("text")?,
                column: col,
            },
            "attr" => {
                let name = self.call_arg("attr")?;
                self.comparison(name, col)?
            }
            "class" | "level" | "id" | "category" | "label" => {
                let ne = self.eq_op(&lower)?;
                let (v, vc) = self.value(&format!("`{lower}=`"))?;
                let term = match lower.as_str() {
                    "class" => Term::Class {
                        name: v,
                        column: col,
                    },
                    "level" => Term::Level {
                        name: v,
                        column: col,
                    },
                    "id" => Term::Id { id: v, column: col },
                    "category" => Term::Category {
                        name: v,
                        column: col,
                    },
                    _ => match v.parse::<i64>() {
                        Ok(id) => Term::Label { id, column: col },
                        Err(_) => {
                            return self.err(
                                vc,
                                format!("`label=` needs an integer label id, found `{v}`"),
                            );
                        }
                    },
                };
                // `x != v` is `not x = v`.
                if ne {
                    return Ok(Expr::Not(Box::new(Expr::Term(term))));
                }
                term
            }
            _ => self.comparison(word, col)?,
        };
        Ok(Expr::Term(term))
    }

    fn comparison(&mut self, name: String, col: usize) -> Result<Term, ParseError> {
        let (t, c) = self.next();
        let op = match t {
            Tok::Op(o) => o,
            t => {
                return self.err(
                    c,
                    format!(
                        "expected a comparison (= != < <= > >=) after the attribute `{name}`, found {}",
                        t.describe()
                    ),
                );
            }
        };
        let (t, vc) = self.next();
        let value = match t {
            Tok::Str(s) => Literal::Text(s),
            Tok::Word(w) => match split_number(&w)
                .filter(|(_, rest)| rest.is_empty() || rest.starts_with(char::is_alphabetic))
            {
                Some((v, rest)) => {
                    let text = w[..w.len() - rest.len()].to_string();
                    let mut unit = (!rest.is_empty()).then(|| rest.to_string());
                    let mut uc = vc;
                    // A word right after the number that is not a keyword is its unit.
                    if unit.is_none()
                        && let (Tok::Word(u), c) = self.peek().clone()
                        && !KEYWORDS.contains(&u.to_ascii_lowercase().as_str())
                    {
                        unit = Some(u);
                        uc = c;
                        self.next();
                    }
                    if let Some(u) = &unit
                        && !super::units::is_known(u)
                    {
                        return self.err(
                            uc,
                            format!(
                                "unknown unit `{u}` after the number (known: {}); quote the value to compare text",
                                super::units::KNOWN.join(" ")
                            ),
                        );
                    }
                    Literal::Number {
                        value: v,
                        text,
                        unit,
                    }
                }
                None => {
                    if KEYWORDS.contains(&w.to_ascii_lowercase().as_str()) {
                        return self.err(
                            vc,
                            format!("expected a value after `{}`, found the keyword `{w}` (quote it to compare text)", op.as_str()),
                        );
                    }
                    Literal::Text(w)
                }
            },
            t => {
                return self.err(
                    vc,
                    format!(
                        "expected a value after `{name}{}`, found {}",
                        op.as_str(),
                        t.describe()
                    ),
                );
            }
        };
        Ok(Term::Attr {
            name,
            op,
            value,
            column: col,
        })
    }
}

/// Parses a selection expression.
pub fn parse(text: &str) -> Result<Expr, ParseError> {
    let toks = lex(text)?;
    if toks.len() == 1 {
        return Err(ParseError {
            column: 1,
            why: "empty selection".into(),
        });
    }
    let mut p = Parser {
        toks,
        pos: 0,
        depth: 0,
        terms: 0,
    };
    let e = p.expr()?;
    let (t, c) = p.next();
    if t != Tok::End {
        let why = match t {
            Tok::RParen => "`)` without a matching `(`".to_string(),
            t => format!("expected `and`, `or` or the end, found {}", t.describe()),
        };
        return Err(ParseError { column: c, why });
    }
    Ok(e)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn attr(name: &str, op: Op, value: Literal) -> Expr {
        Expr::Term(Term::Attr {
            name: name.into(),
            op,
            value,
            column: 0,
        })
    }

    /// The tree with every column set to 0 (columns are checked separately).
    fn strip(e: Expr) -> Expr {
        match e {
            Expr::And(a, b) => Expr::And(Box::new(strip(*a)), Box::new(strip(*b))),
            Expr::Or(a, b) => Expr::Or(Box::new(strip(*a)), Box::new(strip(*b))),
            Expr::Not(a) => Expr::Not(Box::new(strip(*a))),
            Expr::Term(mut t) => {
                match &mut t {
                    Term::Class { column, .. }
                    | Term::Level { column, .. }
                    | Term::Id { column, .. }
                    | Term::Within { column, .. }
                    | Term::Category { column, .. }
                    | Term::Label { column, .. }
                    | Term::Text { column, .. }
                    | Term::Attr { column, .. } => *column = 0,
                }
                Expr::Term(t)
            }
            e => e,
        }
    }

    fn p(s: &str) -> Expr {
        strip(parse(s).unwrap_or_else(|e| panic!("{s}: {e}")))
    }

    fn class(n: &str) -> Expr {
        Expr::Term(Term::Class {
            name: n.into(),
            column: 0,
        })
    }

    #[test]
    fn precedence_not_and_or() {
        // not > and > or, left-associative.
        let e = p("class=Window or class=Door and not level=part");
        let want = Expr::Or(
            Box::new(class("Window")),
            Box::new(Expr::and(
                class("Door"),
                Expr::Not(Box::new(Expr::Term(Term::Level {
                    name: "part".into(),
                    column: 0,
                }))),
            )),
        );
        assert_eq!(e, want);
        let e = p("(class=Window or class=Door) and within(B1)");
        assert_eq!(
            e,
            Expr::and(
                Expr::Or(Box::new(class("Window")), Box::new(class("Door"))),
                Expr::Term(Term::Within {
                    id: "B1".into(),
                    column: 0
                })
            )
        );
        assert_eq!(p("CLASS = Window AND Not class!=Door"), {
            Expr::and(
                class("Window"),
                Expr::Not(Box::new(Expr::Not(Box::new(class("Door"))))),
            )
        });
    }

    #[test]
    fn comparisons_numbers_units_and_strings() {
        let num = |v: f64, t: &str, u: Option<&str>| Literal::Number {
            value: v,
            text: t.into(),
            unit: u.map(String::from),
        };
        assert_eq!(
            p("measuredHeight>10"),
            attr("measuredHeight", Op::Gt, num(10.0, "10", None))
        );
        assert_eq!(
            p("measuredHeight >= 1200cm"),
            attr("measuredHeight", Op::Ge, num(1200.0, "1200", Some("cm")))
        );
        assert_eq!(
            p("measuredHeight<=1.5 km"),
            attr("measuredHeight", Op::Le, num(1.5, "1.5", Some("km")))
        );
        assert_eq!(p("h<-2.5e1"), attr("h", Op::Lt, num(-25.0, "-2.5e1", None)));
        assert_eq!(
            p("dataAvailable=Sufficient"),
            attr("dataAvailable", Op::Eq, Literal::Text("Sufficient".into()))
        );
        assert_eq!(
            p("creationDate >= 2020-09-01"),
            attr("creationDate", Op::Ge, Literal::Text("2020-09-01".into()))
        );
        assert_eq!(
            p("name != 'my \\'house\\''"),
            attr("name", Op::Ne, Literal::Text("my 'house'".into()))
        );
        assert_eq!(
            p("@cityeditor:layer=\"A B\""),
            attr("@cityeditor:layer", Op::Eq, Literal::Text("A B".into()))
        );
        assert_eq!(
            p("attr(class) = x"),
            attr("class", Op::Eq, Literal::Text("x".into()))
        );
        assert_eq!(p("a<>1"), attr("a", Op::Ne, num(1.0, "1", None)));
        assert_eq!(p("a==1"), attr("a", Op::Eq, num(1.0, "1", None)));
        // A unit word after a number that is a keyword stays a keyword.
        assert_eq!(
            p("h>10 and class=Window"),
            Expr::and(attr("h", Op::Gt, num(10.0, "10", None)), class("Window"))
        );
        assert_eq!(
            p("text(\"a car\")"),
            Expr::Term(Term::Text {
                prompt: "a car".into(),
                column: 0
            })
        );
        assert_eq!(
            p("label=10003"),
            Expr::Term(Term::Label {
                id: 10003,
                column: 0
            })
        );
    }

    #[test]
    fn errors_point_at_the_column() {
        let e = |s: &str| parse(s).unwrap_err();
        let x = e("class=Window and (");
        assert_eq!(x.column, 19, "{x}");
        assert!(x.why.contains("expected a term"), "{x}");
        let x = e("measuredHeight >");
        assert_eq!(x.column, 17);
        assert!(x.why.contains("expected a value"), "{x}");
        let x = e("measuredHeight 10");
        assert_eq!(x.column, 16);
        assert!(x.why.contains("comparison"), "{x}");
        let x = e("class > Window");
        assert_eq!(x.column, 7);
        assert!(x.why.contains("`=` or `!=` only"), "{x}");
        let x = e("(class=Window");
        assert_eq!(x.column, 14);
        assert!(x.why.contains("close the `(` of column 1"), "{x}");
        let x = e("class=Window)");
        assert_eq!(x.column, 13);
        assert!(x.why.contains("without a matching"), "{x}");
        let x = e("h > 10 furlongs");
        assert_eq!(x.column, 8, "{x}");
        assert!(x.why.contains("unknown unit `furlongs`"), "{x}");
        let x = e("h > 10 m m");
        assert_eq!(x.column, 10, "{x}");
        assert!(x.why.contains("expected `and`"), "{x}");
        let x = e("h > 10furlongs");
        assert_eq!(x.column, 5);
        assert!(x.why.contains("unknown unit `furlongs`"), "{x}");
        let x = e("name = 'open");
        assert_eq!(x.column, 8);
        assert!(x.why.contains("unterminated"), "{x}");
        let x = e("a ! b");
        assert_eq!(x.column, 3);
        let x = e("label=x");
        assert_eq!(x.column, 7);
        let x = e("within B");
        assert_eq!(x.column, 8);
        let x = e("  ");
        assert!(x.why.contains("empty"));
        let x = e("and class=Window");
        assert_eq!(x.column, 1);
        let x = e("h > and");
        assert!(x.why.contains("keyword"), "{x}");
        // Columns count characters, not bytes.
        let x = e("name='é' >");
        assert_eq!(x.column, 10, "{x}");
    }

    #[test]
    fn nesting_and_length_are_bounded_before_the_stack_is() {
        let e = |s: &str| parse(s).unwrap_err();
        // 100 000 `(` overflowed the stack (an abort, in the viewer a dead server).
        let deep = format!("{}class=Window{}", "(".repeat(100_000), ")".repeat(100_000));
        let x = e(&deep);
        assert!(x.why.contains("nested deeper than 128"), "{x}");
        assert_eq!(x.column, MAX_NESTING + 1);
        let x = e(&format!("{}class=Window", "not ".repeat(1000)));
        assert!(x.why.contains("nested deeper"), "{x}");
        // At the bound: parsed, and as deep as written.
        let ok = format!(
            "{}class=Window{}",
            "(".repeat(MAX_NESTING),
            ")".repeat(MAX_NESTING)
        );
        assert_eq!(p(&ok), p("class=Window"));
        let chain = |n: usize| vec!["label=1"; n].join(" or ");
        assert!(parse(&chain(MAX_TERMS)).is_ok());
        let x = e(&chain(MAX_TERMS + 1));
        assert!(x.why.contains("more than 4096 terms"), "{x}");
    }

    #[test]
    fn display_parses_back_to_the_same_tree() {
        for s in [
            "class=Window and within(\"DEBY 1\")",
            "not (measuredHeight > 10 m or name = 'a \"b\"') and level=surface",
            "attr(class)=x or text('a car') or label=3 or category=car or id=X",
            "creationDate>=2020-09-01",
        ] {
            let e = p(s);
            let again = p(&e.to_string());
            assert_eq!(e, again, "{s} → {e}");
        }
    }
}
