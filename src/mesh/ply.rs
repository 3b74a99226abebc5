//! PLY, binary (both byte orders) and ASCII: vertices with optional colours, faces as lists.

use super::{MAX_TRIANGLES, MeshError, Parsed, perr};

#[derive(Clone, Copy, PartialEq, Debug)]
enum PlyType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl PlyType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
    fn read(self, b: &[u8], big: bool) -> f64 {
        macro_rules! rd {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                (if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => rd!(i16, 2),
            Self::U16 => rd!(u16, 2),
            Self::I32 => rd!(i32, 4),
            Self::U32 => rd!(u32, 4),
            Self::F32 => rd!(f32, 4),
            Self::F64 => rd!(f64, 8),
        }
    }
}

#[derive(Debug)]
enum PlyProp {
    Scalar(String, PlyType),
    List(String, PlyType, PlyType),
}

struct PlyElement {
    name: String,
    count: usize,
    props: Vec<PlyProp>,
}

pub(super) fn parse(bytes: &[u8]) -> Result<Parsed, MeshError> {
    const F: &str = "PLY";
    let header_end = bytes
        .windows(10)
        .position(|w| w == b"end_header")
        .ok_or_else(|| perr(F, "no end_header line"))?;
    let mut body_start = header_end + 10;
    while body_start < bytes.len() && (bytes[body_start] == b'\r' || bytes[body_start] == b' ') {
        body_start += 1;
    }
    if body_start < bytes.len() && bytes[body_start] == b'\n' {
        body_start += 1;
    }
    let header = std::str::from_utf8(&bytes[..header_end]).map_err(|_| perr(F, "header is not text"))?;
    let mut format = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    for line in header.lines() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.first().copied() {
            Some("format") => format = w.get(1).map(|s| s.to_string()),
            Some("element") => {
                let name = w.get(1).ok_or_else(|| perr(F, "element without a name"))?.to_string();
                let count: usize = w
                    .get(2)
                    .and_then(|s| s.parse().ok())
                    .ok_or_else(|| perr(F, "element count"))?;
                if count > 10 * MAX_TRIANGLES {
                    return Err(MeshError::TooManyTriangles(count));
                }
                elements.push(PlyElement {
                    name,
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let el = elements.last_mut().ok_or_else(|| perr(F, "property before element"))?;
                if w.get(1) == Some(&"list") {
                    let ct = w
                        .get(2)
                        .and_then(|s| PlyType::parse(s))
                        .ok_or_else(|| perr(F, "list count type"))?;
                    let it = w
                        .get(3)
                        .and_then(|s| PlyType::parse(s))
                        .ok_or_else(|| perr(F, "list item type"))?;
                    el.props
                        .push(PlyProp::List(w.get(4).unwrap_or(&"").to_string(), ct, it));
                } else {
                    let t = w
                        .get(1)
                        .and_then(|s| PlyType::parse(s))
                        .ok_or_else(|| perr(F, format!("property type in '{line}'")))?;
                    el.props.push(PlyProp::Scalar(w.get(2).unwrap_or(&"").to_string(), t));
                }
            }
            _ => {}
        }
    }
    let format = format.ok_or_else(|| perr(F, "no format line"))?;
    let body = &bytes[body_start..];
    let mut verts = Vec::new();
    let mut cols = Vec::new();
    let mut has_color = false;
    let mut tris = Vec::new();

    // One record reader for both encodings: yields property values element by element.
    enum Src<'a> {
        Ascii(std::str::SplitAsciiWhitespace<'a>),
        Bin { data: &'a [u8], pos: usize, big: bool },
    }
    impl Src<'_> {
        fn next(&mut self, t: PlyType) -> Result<f64, MeshError> {
            match self {
                Src::Ascii(it) => it
                    .next()
                    .and_then(|s| s.parse::<f64>().ok())
                    .ok_or_else(|| perr("PLY", "truncated or non-numeric ASCII body")),
                Src::Bin { data, pos, big } => {
                    let n = t.size();
                    if *pos + n > data.len() {
                        return Err(perr("PLY", "truncated binary body"));
                    }
                    let v = t.read(&data[*pos..*pos + n], *big);
                    *pos += n;
                    Ok(v)
                }
            }
        }
    }
    let mut src = match format.as_str() {
        "ascii" => Src::Ascii(
            std::str::from_utf8(body)
                .map_err(|_| perr(F, "ASCII body is not text"))?
                .split_ascii_whitespace(),
        ),
        "binary_little_endian" => Src::Bin {
            data: body,
            pos: 0,
            big: false,
        },
        "binary_big_endian" => Src::Bin {
            data: body,
            pos: 0,
            big: true,
        },
        other => return Err(perr(F, format!("unsupported format {other}"))),
    };
    for el in &elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        if is_vertex {
            has_color = el
                .props
                .iter()
                .any(|p| matches!(p, PlyProp::Scalar(n, _) if n == "red"));
            verts.reserve(el.count);
        }
        for _ in 0..el.count {
            let mut xyz = [0f32; 3];
            let mut rgb = [160u8; 3];
            for p in &el.props {
                match p {
                    PlyProp::Scalar(name, t) => {
                        let v = src.next(*t)?;
                        if is_vertex {
                            match name.as_str() {
                                "x" => xyz[0] = v as f32,
                                "y" => xyz[1] = v as f32,
                                "z" => xyz[2] = v as f32,
                                "red" | "r" => rgb[0] = v.clamp(0.0, 255.0) as u8,
                                "green" | "g" => rgb[1] = v.clamp(0.0, 255.0) as u8,
                                "blue" | "b" => rgb[2] = v.clamp(0.0, 255.0) as u8,
                                _ => {}
                            }
                        }
                    }
                    PlyProp::List(name, ct, it) => {
                        let n = src.next(*ct)?;
                        if !(0.0..=1024.0).contains(&n) {
                            return Err(perr(F, format!("list of {n} items")));
                        }
                        let mut idx = Vec::with_capacity(n as usize);
                        for _ in 0..n as usize {
                            idx.push(src.next(*it)?);
                        }
                        if is_face && (name == "vertex_indices" || name == "vertex_index") {
                            if idx.iter().any(|&i| i < 0.0) {
                                return Err(perr(F, "negative vertex index"));
                            }
                            for k in 1..idx.len().saturating_sub(1) {
                                tris.push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
                                if tris.len() > MAX_TRIANGLES {
                                    return Err(MeshError::TooManyTriangles(tris.len()));
                                }
                            }
                        }
                    }
                }
            }
            if is_vertex {
                verts.push(xyz);
                cols.push(rgb);
            }
        }
    }
    Ok((verts, has_color.then_some(cols), tris))
}
