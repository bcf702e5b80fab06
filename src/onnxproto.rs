//! The ONNX model format (protobuf `ModelProto`), read just far enough to keep a subset of a
//! graph's outputs: the nodes, initializers and outputs that no kept output depends on are
//! dropped, everything else is copied byte for byte.
//!
//! Why: ONNX Runtime runs every node of a graph whatever outputs a call asks for. SAM's decoder
//! export computes `masks` (an upsampling of every prompt's four masks to 1024² and then to the
//! image size) after the `low_res_masks` that `segment` reads; a graph without that tail computes
//! the same two outputs, bit for bit, with less work (docs/segment.md).
//!
//! [`read_graph`] reads the nodes (names, operators, inputs, outputs) and the `float`
//! initializers of a graph, for code that computes a known network natively from an export's
//! weights (`segment`'s SAM decoder).
//!
//! Protobuf wire format: each field is a varint key `(number << 3) | type` followed by a varint
//! (type 0), 8 bytes (1), a varint length and that many bytes (2) or 4 bytes (5). Field numbers
//! are those of `onnx.proto3`: `ModelProto.graph` 7; `GraphProto.node` 1, `initializer` 5,
//! `input` 11, `output` 12; `NodeProto.input` 1, `output` 2, `attribute` 5;
//! `AttributeProto.g` 6, `graphs` 11; `TensorProto.name` 8, `external_data` 13, `data_location`
//! 14; `ValueInfoProto.name` 1.

use std::collections::HashSet;

/// Why a model cannot be pruned (the caller then loads the file as it is).
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum OnnxError {
    #[error("not a protobuf message: {0}")]
    Wire(&'static str),
    #[error("the model has no graph")]
    NoGraph,
    #[error("the graph has no output `{0}`")]
    NoOutput(String),
    #[error("a node holds a subgraph (control flow), whose outer-scope inputs are not traced")]
    Subgraph,
    #[error("an initializer's data is stored outside the model file")]
    ExternalData,
    #[error("initializer `{name}`: {why}")]
    Tensor { name: String, why: String },
}

/// A graph node as [`read_graph`] gives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GraphNode {
    pub name: String,
    pub op_type: String,
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
}

/// A `float` initializer: its dimensions and values (row-major).
#[derive(Debug, Clone, PartialEq)]
pub struct FloatTensor {
    pub dims: Vec<usize>,
    pub data: Vec<f32>,
}

/// The nodes and `float` initializers of a model's graph (initializers of other types are
/// left out).
#[derive(Debug, Clone, Default)]
pub struct Graph {
    pub nodes: Vec<GraphNode>,
    pub initializers: std::collections::HashMap<String, FloatTensor>,
}

/// The largest initializer [`read_graph`] accepts (elements), checked before allocating.
const MAX_TENSOR: usize = 1 << 30;

/// The nodes and `float` initializers of `model`. Sizes are checked against the data before
/// anything is allocated; external data, a wrong data length or a truncated message are
/// errors.
pub fn read_graph(model: &[u8]) -> Result<Graph, OnnxError> {
    let top = fields(model)?;
    let graphs = bytes_of(model, &top, 7);
    let [graph] = graphs.as_slice() else {
        return Err(OnnxError::NoGraph);
    };
    let gfs = fields(graph)?;
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    let mut out = Graph::default();
    for nb in bytes_of(graph, &gfs, 1) {
        let nfs = fields(nb)?;
        out.nodes.push(GraphNode {
            name: bytes_of(nb, &nfs, 3)
                .last()
                .map(|b| text(b))
                .unwrap_or_default(),
            op_type: bytes_of(nb, &nfs, 4)
                .last()
                .map(|b| text(b))
                .unwrap_or_default(),
            inputs: bytes_of(nb, &nfs, 1).into_iter().map(text).collect(),
            outputs: bytes_of(nb, &nfs, 2).into_iter().map(text).collect(),
        });
    }
    for tb in bytes_of(graph, &gfs, 5) {
        let tfs = fields(tb)?;
        let name = bytes_of(tb, &tfs, 8)
            .last()
            .map(|b| text(b))
            .unwrap_or_default();
        let bad = |why: &str| OnnxError::Tensor {
            name: name.clone(),
            why: why.to_string(),
        };
        let mut data_type = 0u64;
        let mut dims = Vec::new();
        for f in &tfs {
            let mut p = f.payload.0;
            match (f.number, f.wire) {
                (2, 0) => data_type = varint(tb, &mut p)?,
                (1, 0) => dims.push(varint(tb, &mut p)?),
                (1, 2) => {
                    while p < f.payload.1 {
                        dims.push(varint(&tb[..f.payload.1], &mut p)?);
                    }
                }
                (13, _) => return Err(OnnxError::ExternalData),
                (14, 0) if varint(tb, &mut p)? == 1 => return Err(OnnxError::ExternalData),
                _ => {}
            }
        }
        if data_type != 1 {
            continue; // not FLOAT
        }
        let dims: Vec<usize> = dims
            .into_iter()
            .map(|d| usize::try_from(d).map_err(|_| bad("dimension out of range")))
            .collect::<Result<_, _>>()?;
        let count = dims
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .filter(|&c| c <= MAX_TENSOR)
            .ok_or_else(|| bad("too many elements"))?;
        let raw = bytes_of(tb, &tfs, 9);
        let data: Vec<f32> = if let Some(r) = raw.last() {
            if r.len() != count * 4 {
                return Err(bad(&format!(
                    "{} bytes of raw data for {count} values",
                    r.len()
                )));
            }
            r.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        } else {
            // float_data (field 4): packed (wire 2) or one fixed32 per value (wire 5)
            let mut v = Vec::new();
            for f in tfs.iter().filter(|f| f.number == 4) {
                let b = &tb[f.payload.0..f.payload.1];
                if b.len() % 4 != 0 || v.len() + b.len() / 4 > count {
                    return Err(bad("float_data does not match the dimensions"));
                }
                v.extend(
                    b.chunks_exact(4)
                        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
                );
            }
            if v.len() != count {
                return Err(bad(&format!("{} values for {count}", v.len())));
            }
            v
        };
        out.initializers.insert(name, FloatTensor { dims, data });
    }
    Ok(out)
}

/// One field of a message: its number, wire type and the byte range of the whole field (key
/// included) and of its payload.
#[derive(Debug, Clone, Copy)]
struct Field {
    number: u64,
    wire: u8,
    whole: (usize, usize),
    payload: (usize, usize),
}

fn varint(buf: &[u8], pos: &mut usize) -> Result<u64, OnnxError> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let b = *buf.get(*pos).ok_or(OnnxError::Wire("truncated varint"))?;
        *pos += 1;
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return Ok(v);
        }
    }
    Err(OnnxError::Wire("varint longer than 10 bytes"))
}

/// The fields of one message, in order.
fn fields(buf: &[u8]) -> Result<Vec<Field>, OnnxError> {
    let mut out = Vec::new();
    let mut pos = 0;
    while pos < buf.len() {
        let start = pos;
        let key = varint(buf, &mut pos)?;
        let (number, wire) = (key >> 3, (key & 7) as u8);
        if number == 0 {
            return Err(OnnxError::Wire("field number 0"));
        }
        let payload = match wire {
            0 => {
                let s = pos;
                varint(buf, &mut pos)?;
                (s, pos)
            }
            1 | 5 => {
                let n = if wire == 1 { 8 } else { 4 };
                let end = pos
                    .checked_add(n)
                    .filter(|&e| e <= buf.len())
                    .ok_or(OnnxError::Wire("truncated fixed-size field"))?;
                let s = pos;
                pos = end;
                (s, end)
            }
            2 => {
                let len = varint(buf, &mut pos)?;
                let end = usize::try_from(len)
                    .ok()
                    .and_then(|l| pos.checked_add(l))
                    .filter(|&e| e <= buf.len())
                    .ok_or(OnnxError::Wire("length past the end of the message"))?;
                let s = pos;
                pos = end;
                (s, end)
            }
            _ => return Err(OnnxError::Wire("unsupported wire type (groups)")),
        };
        out.push(Field {
            number,
            wire,
            whole: (start, pos),
            payload,
        });
    }
    Ok(out)
}

/// The length-delimited fields `number` of a message, as byte slices.
fn bytes_of<'a>(buf: &'a [u8], fs: &[Field], number: u64) -> Vec<&'a [u8]> {
    fs.iter()
        .filter(|f| f.number == number && f.wire == 2)
        .map(|f| &buf[f.payload.0..f.payload.1])
        .collect()
}

/// The string field `number` of a message (the last one, as protobuf merges), or "".
fn string_of(buf: &[u8], number: u64) -> Result<String, OnnxError> {
    let fs = fields(buf)?;
    Ok(bytes_of(buf, &fs, number)
        .last()
        .map(|b| String::from_utf8_lossy(b).into_owned())
        .unwrap_or_default())
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// A node's inputs and outputs.
struct Node {
    inputs: Vec<String>,
    outputs: Vec<String>,
}

/// A node's inputs and outputs; a node that holds a subgraph is refused.
fn node(buf: &[u8]) -> Result<Node, OnnxError> {
    let fs = fields(buf)?;
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    for attr in bytes_of(buf, &fs, 5) {
        let afs = fields(attr)?;
        if afs.iter().any(|f| f.number == 6 || f.number == 11) {
            return Err(OnnxError::Subgraph);
        }
    }
    Ok(Node {
        inputs: bytes_of(buf, &fs, 1).into_iter().map(text).collect(),
        outputs: bytes_of(buf, &fs, 2).into_iter().map(text).collect(),
    })
}

/// The model with only the graph outputs named in `keep` (in the graph's order) and what they
/// depend on: nodes none of whose outputs are needed are dropped, and initializers no kept node
/// reads (unless they are also graph inputs). Graph inputs stay, so a caller feeds the same
/// inputs. Returns the new model's bytes and the names of the outputs dropped.
pub fn keep_outputs(model: &[u8], keep: &[&str]) -> Result<(Vec<u8>, Vec<String>), OnnxError> {
    let top = fields(model)?;
    let graph_fields: Vec<&Field> = top.iter().filter(|f| f.number == 7).collect();
    let [graph_field] = graph_fields.as_slice() else {
        return Err(OnnxError::NoGraph);
    };
    if graph_field.wire != 2 {
        return Err(OnnxError::Wire("graph is not a message"));
    }
    let graph = &model[graph_field.payload.0..graph_field.payload.1];
    let gfs = fields(graph)?;

    // outputs
    let mut out_names = Vec::new();
    for f in gfs.iter().filter(|f| f.number == 12 && f.wire == 2) {
        out_names.push(string_of(&graph[f.payload.0..f.payload.1], 1)?);
    }
    for k in keep {
        if !out_names.iter().any(|n| n == k) {
            return Err(OnnxError::NoOutput((*k).to_string()));
        }
    }
    let dropped: Vec<String> = out_names
        .iter()
        .filter(|n| !keep.contains(&n.as_str()))
        .cloned()
        .collect();

    // nodes, and the values the kept outputs need (to a fixed point: no order is assumed)
    let node_fields: Vec<&Field> = gfs.iter().filter(|f| f.number == 1).collect();
    let nodes = node_fields
        .iter()
        .map(|f| node(&graph[f.payload.0..f.payload.1]))
        .collect::<Result<Vec<_>, _>>()?;
    let mut needed: HashSet<String> = keep.iter().map(|s| s.to_string()).collect();
    let mut live = vec![false; nodes.len()];
    loop {
        let mut changed = false;
        for (i, n) in nodes.iter().enumerate().rev() {
            if !live[i] && n.outputs.iter().any(|o| needed.contains(o)) {
                live[i] = true;
                changed = true;
                for inp in n.inputs.iter().filter(|s| !s.is_empty()) {
                    needed.insert(inp.clone());
                }
            }
        }
        if !changed {
            break;
        }
    }

    // initializers: external data cannot be resolved from memory; unread ones are dropped
    let mut input_names = HashSet::new();
    for f in gfs.iter().filter(|f| f.number == 11 && f.wire == 2) {
        input_names.insert(string_of(&graph[f.payload.0..f.payload.1], 1)?);
    }
    let mut keep_field = vec![true; gfs.len()];
    let mut node_index = 0;
    for (fi, f) in gfs.iter().enumerate() {
        let payload = &graph[f.payload.0..f.payload.1];
        match f.number {
            1 => {
                keep_field[fi] = live[node_index];
                node_index += 1;
            }
            5 if f.wire == 2 => {
                let tfs = fields(payload)?;
                let external = tfs.iter().any(|t| t.number == 13)
                    || tfs.iter().any(|t| {
                        t.number == 14 && t.wire == 0 && {
                            let mut p = t.payload.0;
                            varint(payload, &mut p).is_ok_and(|v| v == 1)
                        }
                    });
                if external {
                    return Err(OnnxError::ExternalData);
                }
                let name = string_of(payload, 8)?;
                keep_field[fi] = needed.contains(&name) || input_names.contains(&name);
            }
            12 if f.wire == 2 => {
                keep_field[fi] = keep.contains(&string_of(payload, 1)?.as_str());
            }
            _ => {}
        }
    }

    let mut new_graph = Vec::with_capacity(graph.len());
    for (f, _) in gfs.iter().zip(&keep_field).filter(|(_, k)| **k) {
        new_graph.extend_from_slice(&graph[f.whole.0..f.whole.1]);
    }
    let mut out = Vec::with_capacity(model.len());
    for f in &top {
        if f.number == 7 {
            put_varint(&mut out, (7 << 3) | 2);
            put_varint(&mut out, new_graph.len() as u64);
            out.extend_from_slice(&new_graph);
        } else {
            out.extend_from_slice(&model[f.whole.0..f.whole.1]);
        }
    }
    Ok((out, dropped))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field_bytes(out: &mut Vec<u8>, number: u64, payload: &[u8]) {
        put_varint(out, (number << 3) | 2);
        put_varint(out, payload.len() as u64);
        out.extend_from_slice(payload);
    }

    fn node_proto(inputs: &[&str], outputs: &[&str], op: &str) -> Vec<u8> {
        let mut n = Vec::new();
        for i in inputs {
            field_bytes(&mut n, 1, i.as_bytes());
        }
        for o in outputs {
            field_bytes(&mut n, 2, o.as_bytes());
        }
        field_bytes(&mut n, 4, op.as_bytes());
        n
    }

    fn named(number: u64, name: &str) -> Vec<u8> {
        let mut v = Vec::new();
        field_bytes(&mut v, number, name.as_bytes());
        v
    }

    /// x → A → a → B → b (output) ; a → C → c (output) ; initializer w read by C only.
    fn model() -> Vec<u8> {
        let mut g = Vec::new();
        field_bytes(&mut g, 1, &node_proto(&["x"], &["a"], "Relu"));
        field_bytes(&mut g, 1, &node_proto(&["a"], &["b"], "Neg"));
        field_bytes(&mut g, 1, &node_proto(&["a", "w"], &["c"], "Add"));
        field_bytes(&mut g, 2, b"g");
        field_bytes(&mut g, 5, &named(8, "w"));
        field_bytes(&mut g, 11, &named(1, "x"));
        field_bytes(&mut g, 12, &named(1, "b"));
        field_bytes(&mut g, 12, &named(1, "c"));
        let mut m = Vec::new();
        put_varint(&mut m, 1 << 3); // ir_version = 8 (varint field)
        put_varint(&mut m, 8);
        field_bytes(&mut m, 7, &g);
        field_bytes(&mut m, 2, b"producer");
        m
    }

    fn outputs_and_ops(m: &[u8]) -> (Vec<String>, Vec<String>, usize) {
        let top = fields(m).unwrap();
        let g = bytes_of(m, &top, 7)[0];
        let gfs = fields(g).unwrap();
        let outs = bytes_of(g, &gfs, 12)
            .into_iter()
            .map(|b| string_of(b, 1).unwrap())
            .collect();
        let ops = bytes_of(g, &gfs, 1)
            .into_iter()
            .map(|b| string_of(b, 4).unwrap())
            .collect();
        (outs, ops, bytes_of(g, &gfs, 5).len())
    }

    #[test]
    fn a_dropped_output_takes_its_own_nodes_and_initializers_with_it() {
        let (m, dropped) = keep_outputs(&model(), &["b"]).unwrap();
        assert_eq!(dropped, vec!["c".to_string()]);
        let (outs, ops, inits) = outputs_and_ops(&m);
        assert_eq!(outs, vec!["b"]);
        assert_eq!(ops, vec!["Relu", "Neg"]);
        assert_eq!(inits, 0);
        // the other top-level fields are copied as they were
        assert_eq!(string_of(&m, 2).unwrap(), "producer");
        let top = fields(&m).unwrap();
        assert_eq!(top[0].number, 1);
        assert_eq!(&m[top[0].payload.0..top[0].payload.1], &[8]);

        let (_, ops, inits) = outputs_and_ops(&keep_outputs(&model(), &["c"]).unwrap().0);
        assert_eq!(ops, vec!["Relu", "Add"]);
        assert_eq!(inits, 1);
        // keeping every output changes nothing
        let (all, dropped) = keep_outputs(&model(), &["b", "c"]).unwrap();
        assert!(dropped.is_empty());
        assert_eq!(all, model());
    }

    #[test]
    fn what_cannot_be_pruned_is_refused() {
        assert_eq!(
            keep_outputs(&model(), &["z"]).unwrap_err(),
            OnnxError::NoOutput("z".into())
        );
        let m = model();
        for cut in [1, 5, m.len() / 2, m.len() - 1] {
            assert!(keep_outputs(&m[..cut], &["b"]).is_err(), "cut at {cut}");
        }
        assert_eq!(keep_outputs(&[], &["b"]).unwrap_err(), OnnxError::NoGraph);
        // a node with a subgraph attribute (If/Loop)
        let mut attr = Vec::new();
        field_bytes(&mut attr, 6, b"");
        let mut n = node_proto(&["x"], &["b"], "If");
        field_bytes(&mut n, 5, &attr);
        let mut g = Vec::new();
        field_bytes(&mut g, 1, &n);
        field_bytes(&mut g, 12, &named(1, "b"));
        let mut sub = Vec::new();
        field_bytes(&mut sub, 7, &g);
        assert_eq!(keep_outputs(&sub, &["b"]).unwrap_err(), OnnxError::Subgraph);
        // external initializer data
        let mut t = named(8, "w");
        put_varint(&mut t, 14 << 3);
        put_varint(&mut t, 1);
        let mut g = Vec::new();
        field_bytes(&mut g, 1, &node_proto(&["w"], &["b"], "Neg"));
        field_bytes(&mut g, 5, &t);
        field_bytes(&mut g, 12, &named(1, "b"));
        let mut ext = Vec::new();
        field_bytes(&mut ext, 7, &g);
        assert_eq!(
            keep_outputs(&ext, &["b"]).unwrap_err(),
            OnnxError::ExternalData
        );
    }

    fn tensor(name: &str, dims: &[u64], raw: Option<&[f32]>, floats: Option<&[f32]>) -> Vec<u8> {
        let mut t = Vec::new();
        for &d in dims {
            put_varint(&mut t, 1 << 3);
            put_varint(&mut t, d);
        }
        put_varint(&mut t, 2 << 3); // data_type FLOAT
        put_varint(&mut t, 1);
        if let Some(v) = floats {
            let b: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
            field_bytes(&mut t, 4, &b);
        }
        field_bytes(&mut t, 8, name.as_bytes());
        if let Some(v) = raw {
            let b: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
            field_bytes(&mut t, 9, &b);
        }
        t
    }

    fn graph_model(inits: &[Vec<u8>]) -> Vec<u8> {
        let mut g = Vec::new();
        let mut n = node_proto(&["x", "w"], &["y"], "MatMul");
        field_bytes(&mut n, 3, b"/lin/MatMul");
        field_bytes(&mut g, 1, &n);
        for t in inits {
            field_bytes(&mut g, 5, t);
        }
        let mut m = Vec::new();
        field_bytes(&mut m, 7, &g);
        m
    }

    #[test]
    fn the_graph_reader_gives_nodes_and_float_initializers() {
        let m = graph_model(&[
            tensor("w", &[2, 3], Some(&[1.0, 2.0, 3.0, 4.0, 5.0, -6.5]), None),
            tensor("b", &[3], None, Some(&[0.5, 0.25, -1.0])),
        ]);
        let g = read_graph(&m).unwrap();
        assert_eq!(
            g.nodes,
            vec![GraphNode {
                name: "/lin/MatMul".into(),
                op_type: "MatMul".into(),
                inputs: vec!["x".into(), "w".into()],
                outputs: vec!["y".into()],
            }]
        );
        assert_eq!(g.initializers["w"].dims, vec![2, 3]);
        assert_eq!(
            g.initializers["w"].data,
            vec![1.0, 2.0, 3.0, 4.0, 5.0, -6.5]
        );
        assert_eq!(g.initializers["b"].data, vec![0.5, 0.25, -1.0]);
        // data that does not fill the dimensions, or a size past the limit, is refused
        let short = graph_model(&[tensor("w", &[2, 3], Some(&[1.0; 5]), None)]);
        assert!(matches!(read_graph(&short), Err(OnnxError::Tensor { .. })));
        let huge = graph_model(&[tensor("w", &[1 << 20, 1 << 20], Some(&[1.0]), None)]);
        assert!(matches!(read_graph(&huge), Err(OnnxError::Tensor { .. })));
        for cut in [3, m.len() / 2, m.len() - 1] {
            assert!(read_graph(&m[..cut]).is_err(), "cut at {cut}");
        }
    }
}
