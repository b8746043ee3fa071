//! 3MF decoding (3MF core specification): the zip package, the root model part named by
//! `_rels/.rels` (default `3D/3dmodel.model`), mesh objects, component references with
//! their transforms, and build items with theirs. The model's `unit` attribute is converted
//! to millimetres. Materials, colours and the production extension's external model parts
//! (`p:path`) are not read; the latter is refused with a message.

use super::{Mesh, MeshError, MeshLimits};
use glam::{DAffine3, DMat3, DVec3};
use quick_xml::events::{BytesStart, Event};
use std::collections::HashMap;
use std::io::Read;

const DEFAULT_MODEL: &str = "3D/3dmodel.model";
/// Component references deeper than this are refused (they are also how a cycle shows).
const MAX_COMPONENT_DEPTH: usize = 32;

#[derive(Default)]
struct Object {
    vertices: Vec<DVec3>,
    triangles: Vec<[u32; 3]>,
    components: Vec<(u64, DAffine3)>,
}

pub(super) fn load(bytes: &[u8], limits: &MeshLimits) -> Result<Mesh, MeshError> {
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes))
        .map_err(|e| MeshError::ThreeMfZip(e.to_string()))?;
    let model_path = root_model_path(&mut zip, limits)?;
    let text = read_part(&mut zip, &model_path, limits)?
        .ok_or_else(|| MeshError::ThreeMfNoModel(model_path.clone()))?;
    parse_model(&text, &model_path, limits)
}

fn read_part(
    zip: &mut zip::ZipArchive<std::io::Cursor<&[u8]>>,
    name: &str,
    limits: &MeshLimits,
) -> Result<Option<String>, MeshError> {
    let Some(index) = zip.index_for_name(name).or_else(|| {
        // Part names are case-insensitive in OPC.
        (0..zip.len())
            .find(|&i| matches!(zip.name_for_index(i), Some(Ok(n)) if n.eq_ignore_ascii_case(name)))
    }) else {
        return Ok(None);
    };
    let file = zip
        .by_index(index)
        .map_err(|e| MeshError::ThreeMfZip(format!("{name}: {e}")))?;
    if file.size() > limits.max_bytes {
        return Err(MeshError::TooLarge {
            size: file.size(),
            limit: limits.max_bytes,
        });
    }
    let mut buf = Vec::new();
    // Never trust the declared size: read at most one byte over the limit.
    file.take(limits.max_bytes + 1)
        .read_to_end(&mut buf)
        .map_err(|e| MeshError::ThreeMfZip(format!("{name}: {e}")))?;
    if buf.len() as u64 > limits.max_bytes {
        return Err(MeshError::TooLarge {
            size: buf.len() as u64,
            limit: limits.max_bytes,
        });
    }
    String::from_utf8(buf)
        .map(Some)
        .map_err(|e| MeshError::ThreeMf {
            part: name.to_string(),
            message: format!("not UTF-8 text: {e}"),
        })
}

fn root_model_path(
    zip: &mut zip::ZipArchive<std::io::Cursor<&[u8]>>,
    limits: &MeshLimits,
) -> Result<String, MeshError> {
    let Some(rels) = read_part(zip, "_rels/.rels", limits)? else {
        return Ok(DEFAULT_MODEL.to_string());
    };
    let mut reader = quick_xml::Reader::from_str(&rels);
    loop {
        match reader.read_event() {
            Ok(Event::Start(e)) | Ok(Event::Empty(e))
                if e.local_name().as_ref() == "Relationship" =>
            {
                let ty = attr(&e, "Type").unwrap_or_default();
                if ty.ends_with("/3dmodel") {
                    if let Some(target) = attr(&e, "Target") {
                        return Ok(target.trim_start_matches('/').to_string());
                    }
                }
            }
            Ok(Event::Eof) | Err(_) => return Ok(DEFAULT_MODEL.to_string()),
            _ => {}
        }
    }
}

fn attr(e: &BytesStart, name: &str) -> Option<String> {
    e.attributes()
        .flatten()
        .find(|a| a.key.local_name().as_ref() == name)
        .map(|a| a.value.trim().to_string())
}

fn unit_scale(unit: &str) -> Option<f64> {
    Some(match unit {
        "micron" => 0.001,
        "millimeter" => 1.0,
        "centimeter" => 10.0,
        "inch" => 25.4,
        "foot" => 304.8,
        "meter" => 1000.0,
        _ => return None,
    })
}

/// A 3MF transform: 12 numbers, row-major 4×3, points as row vectors.
fn parse_transform(s: &str) -> Option<DAffine3> {
    let v: Vec<f64> = s
        .split_ascii_whitespace()
        .map(|t| t.parse::<f64>().ok().filter(|x| x.is_finite()))
        .collect::<Option<Vec<_>>>()?;
    if v.len() != 12 {
        return None;
    }
    let m = DMat3::from_cols(
        DVec3::new(v[0], v[1], v[2]),
        DVec3::new(v[3], v[4], v[5]),
        DVec3::new(v[6], v[7], v[8]),
    );
    Some(DAffine3 {
        matrix3: m,
        translation: DVec3::new(v[9], v[10], v[11]),
    })
}

/// Read a model part's objects and build items, and emit the build as one mesh in mm.
fn parse_model(text: &str, part: &str, limits: &MeshLimits) -> Result<Mesh, MeshError> {
    let mut reader = quick_xml::Reader::from_str(text);
    let mut model = ModelReader::new(part, limits);
    loop {
        let event = reader
            .read_event()
            .map_err(|e| xml_error(part, &reader, format!("XML error: {e}")))?;
        match event {
            Event::Eof => break,
            Event::Start(e) => model.element(&e, false, &reader)?,
            Event::Empty(e) => model.element(&e, true, &reader)?,
            Event::End(e) => model.end(e.local_name().as_ref()),
            _ => {}
        }
    }
    model.into_mesh()
}

/// What has been read of a model part so far.
struct ModelReader<'a> {
    part: &'a str,
    limits: &'a MeshLimits,
    /// Millimetres per model unit.
    scale: f64,
    saw_model: bool,
    objects: HashMap<u64, Object>,
    /// The object whose elements are being read, with its id.
    current: Option<(u64, Object)>,
    /// Build items: object id and transform.
    items: Vec<(u64, DAffine3)>,
    in_build: bool,
    /// Vertices read in all objects, against the limit of 3 × max_triangles.
    vertices_read: u64,
}

type XmlReader<'t> = quick_xml::Reader<&'t [u8]>;

/// An XML error in `part` at the reader's position.
fn xml_error(part: &str, reader: &XmlReader, message: String) -> MeshError {
    MeshError::ThreeMfXml {
        part: part.to_string(),
        message,
        offset: reader.buffer_position(),
    }
}

impl<'a> ModelReader<'a> {
    fn new(part: &'a str, limits: &'a MeshLimits) -> Self {
        ModelReader {
            part,
            limits,
            scale: 1.0,
            saw_model: false,
            objects: HashMap::new(),
            current: None,
            items: Vec::new(),
            in_build: false,
            vertices_read: 0,
        }
    }

    /// An element's start (`is_empty`: it has no content and no end).
    fn element(
        &mut self,
        e: &BytesStart,
        is_empty: bool,
        reader: &XmlReader,
    ) -> Result<(), MeshError> {
        let part = self.part;
        match e.local_name().as_ref() {
            "model" => {
                self.saw_model = true;
                let unit = attr(e, "unit").unwrap_or_else(|| "millimeter".to_string());
                self.scale = unit_scale(&unit)
                    .ok_or_else(|| xml_error(part, reader, format!("unknown unit {unit:?}")))?;
            }
            "object" => {
                let id = attr(e, "id")
                    .and_then(|s| s.parse::<u64>().ok())
                    .ok_or_else(|| xml_error(part, reader, "object without a numeric id".into()))?;
                if is_empty {
                    self.objects.insert(id, Object::default());
                } else {
                    self.current = Some((id, Object::default()));
                }
            }
            "vertex" => self.vertex(e, reader)?,
            "triangle" => self.triangle(e, reader)?,
            "component" => self.component(e, reader)?,
            "build" => self.in_build = !is_empty,
            "item" if self.in_build => self.build_item(e, reader)?,
            _ => {}
        }
        Ok(())
    }

    /// An element's end: an object is complete, or the build is.
    fn end(&mut self, name: &str) {
        match name {
            "object" => {
                if let Some((id, obj)) = self.current.take() {
                    self.objects.insert(id, obj);
                }
            }
            "build" => self.in_build = false,
            _ => {}
        }
    }

    /// `<vertex x y z>` of the current object.
    fn vertex(&mut self, e: &BytesStart, reader: &XmlReader) -> Result<(), MeshError> {
        let part = self.part;
        let Some((id, obj)) = self.current.as_mut() else {
            return Ok(());
        };
        let coord = |k: &str| attr(e, k).and_then(|s| s.parse::<f64>().ok());
        let (Some(x), Some(y), Some(z)) = (coord("x"), coord("y"), coord("z")) else {
            return Err(xml_error(
                part,
                reader,
                format!(
                    "object {id} vertex {} lacks a numeric x, y or z",
                    obj.vertices.len()
                ),
            ));
        };
        let v = DVec3::new(x, y, z);
        if !v.is_finite() {
            return Err(MeshError::NotFinite {
                format: "3MF",
                triangle: obj.triangles.len() as u64,
                corner: 0,
                at: Some(format!(
                    "{part} object {id} vertex {}, byte {}",
                    obj.vertices.len(),
                    reader.buffer_position()
                )),
            });
        }
        self.vertices_read += 1;
        if self.vertices_read > 3 * self.limits.max_triangles {
            return Err(xml_error(
                part,
                reader,
                "more vertices than 3 × max_triangles".into(),
            ));
        }
        obj.vertices.push(v);
        Ok(())
    }

    /// `<triangle v1 v2 v3>` of the current object.
    fn triangle(&mut self, e: &BytesStart, reader: &XmlReader) -> Result<(), MeshError> {
        let part = self.part;
        let Some((id, obj)) = self.current.as_mut() else {
            return Ok(());
        };
        let idx = |k: &str| attr(e, k).and_then(|s| s.parse::<u32>().ok());
        let (Some(a), Some(b), Some(c)) = (idx("v1"), idx("v2"), idx("v3")) else {
            return Err(xml_error(
                part,
                reader,
                format!(
                    "object {id} triangle {} lacks numeric v1, v2 or v3",
                    obj.triangles.len()
                ),
            ));
        };
        obj.triangles.push([a, b, c]);
        Ok(())
    }

    /// `<component objectid transform>` of the current object.
    fn component(&mut self, e: &BytesStart, reader: &XmlReader) -> Result<(), MeshError> {
        let part = self.part;
        let Some((id, obj)) = self.current.as_mut() else {
            return Ok(());
        };
        if attr(e, "path").is_some() {
            return Err(xml_error(
                part,
                reader,
                format!("object {id}: components in other model parts (production extension p:path) are not supported"),
            ));
        }
        let target = attr(e, "objectid")
            .and_then(|s| s.parse::<u64>().ok())
            .ok_or_else(|| {
                xml_error(
                    part,
                    reader,
                    format!("object {id}: component without a numeric objectid"),
                )
            })?;
        let t = match attr(e, "transform") {
            None => DAffine3::IDENTITY,
            Some(s) => parse_transform(&s).ok_or_else(|| {
                xml_error(
                    part,
                    reader,
                    format!("object {id}: bad component transform {s:?}"),
                )
            })?,
        };
        obj.components.push((target, t));
        Ok(())
    }

    /// `<item objectid transform>` of the build.
    fn build_item(&mut self, e: &BytesStart, reader: &XmlReader) -> Result<(), MeshError> {
        let part = self.part;
        let target = attr(e, "objectid")
            .and_then(|s| s.parse::<u64>().ok())
            .ok_or_else(|| {
                xml_error(part, reader, "build item without a numeric objectid".into())
            })?;
        let t = match attr(e, "transform") {
            None => DAffine3::IDENTITY,
            Some(s) => parse_transform(&s).ok_or_else(|| {
                xml_error(
                    part,
                    reader,
                    format!("build item {target}: bad transform {s:?}"),
                )
            })?,
        };
        self.items.push((target, t));
        Ok(())
    }

    /// The build's items, their objects expanded, in mm.
    fn into_mesh(self) -> Result<Mesh, MeshError> {
        let part = self.part;
        if !self.saw_model {
            return Err(MeshError::ThreeMfNoModel(format!(
                "a <model> element in {part}"
            )));
        }
        if self.items.is_empty() {
            return Err(MeshError::ThreeMf {
                part: part.to_string(),
                message: "the <build> has no items: nothing to print".into(),
            });
        }
        // The whole expansion counted first, from the objects as read: a few KB of
        // nested components name billions of triangles, refused before any is built.
        let mut counted = HashMap::new();
        let mut count: u64 = 0;
        for &(id, _) in &self.items {
            let n = expanded_triangles(&self.objects, id, 0, &mut counted, part)?;
            count = count.saturating_add(n);
        }
        if count > self.limits.max_triangles_checked() {
            return Err(MeshError::TooManyTriangles {
                count,
                limit: self.limits.max_triangles,
            });
        }
        let mut mesh = Mesh::default();
        let unit = DAffine3::from_scale(DVec3::splat(self.scale));
        for (id, t) in self.items {
            emit(&self.objects, id, unit * t, 0, &mut mesh, part, self.limits)?;
        }
        if mesh.triangles.is_empty() {
            return Err(MeshError::NoTriangles);
        }
        Ok(mesh)
    }
}

/// Object `id`, referenced `depth` components deep: an error for one not defined or
/// nested too deep (a reference cycle).
fn object_at<'a>(
    objects: &'a HashMap<u64, Object>,
    id: u64,
    depth: usize,
    part: &str,
) -> Result<&'a Object, MeshError> {
    let fail = |message: String| MeshError::ThreeMf {
        part: part.to_string(),
        message,
    };
    if depth > MAX_COMPONENT_DEPTH {
        return Err(fail(format!(
            "object {id}: components nested deeper than {MAX_COMPONENT_DEPTH} (a reference cycle?)"
        )));
    }
    objects
        .get(&id)
        .ok_or_else(|| fail(format!("reference to object {id}, which is not defined")))
}

/// The triangles object `id` expands to with its components (saturating), counted
/// without building any; each object counted once (`counted`).
fn expanded_triangles(
    objects: &HashMap<u64, Object>,
    id: u64,
    depth: usize,
    counted: &mut HashMap<u64, u64>,
    part: &str,
) -> Result<u64, MeshError> {
    if let Some(&n) = counted.get(&id) {
        return Ok(n);
    }
    let obj = object_at(objects, id, depth, part)?;
    let mut n = obj.triangles.len() as u64;
    for &(child, _) in &obj.components {
        let c = expanded_triangles(objects, child, depth + 1, counted, part)?;
        n = n.saturating_add(c);
    }
    counted.insert(id, n);
    Ok(n)
}

/// Append object `id` under transform `t` (object space -> mm), expanding components.
fn emit(
    objects: &HashMap<u64, Object>,
    id: u64,
    t: DAffine3,
    depth: usize,
    mesh: &mut Mesh,
    part: &str,
    limits: &MeshLimits,
) -> Result<(), MeshError> {
    let fail = |message: String| MeshError::ThreeMf {
        part: part.to_string(),
        message,
    };
    let obj = object_at(objects, id, depth, part)?;
    let count = mesh.triangles.len() as u64 + obj.triangles.len() as u64;
    if count > limits.max_triangles_checked() {
        return Err(MeshError::TooManyTriangles {
            count,
            limit: limits.max_triangles,
        });
    }
    let n = obj.vertices.len() as u32;
    // Each triangle gets its own corners; repair merges them.
    for (k, tri) in obj.triangles.iter().enumerate() {
        for &i in tri {
            if i >= n {
                return Err(fail(format!(
                    "object {id} triangle {k} refers to vertex {i}, but the object has {n} vertices"
                )));
            }
        }
        let base = mesh.vertices.len() as u32;
        for &i in tri {
            mesh.vertices
                .push(t.transform_point3(obj.vertices[i as usize]));
        }
        mesh.triangles.push([base, base + 1, base + 2]);
    }
    for &(child, ct) in &obj.components {
        emit(objects, child, t * ct, depth + 1, mesh, part, limits)?;
    }
    Ok(())
}
