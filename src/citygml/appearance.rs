//! Appearances (the CityGML app: module): `ParameterizedTexture` with its image, theme and
//! per-ring texture coordinates, and `X3DMaterial` with its diffuse colour, transparency
//! and targets.
use super::model::*;
use super::reader::{Attrs, Parser, Tag};

#[derive(Debug, Clone, Copy)]
pub(super) enum AppField {
    ImageUri,
    Theme,
    Diffuse,
    Transparency,
}

impl Parser {
    pub(super) fn appearance_start(&mut self, local: &str, a: &Attrs) -> Tag {
        match local {
            "ParameterizedTexture" => {
                self.in_material = false;
                self.textures.push(Texture {
                    theme: self.app_theme.clone(),
                    ..Default::default()
                });
                Tag::Texture
            }
            "X3DMaterial" => {
                self.in_material = true;
                self.materials.push(Material::default());
                Tag::Material
            }
            "imageURI" => {
                self.begin_text();
                Tag::AppText(AppField::ImageUri)
            }
            "theme" => {
                self.begin_text();
                Tag::AppText(AppField::Theme)
            }
            "diffuseColor" => {
                self.begin_text();
                Tag::AppText(AppField::Diffuse)
            }
            "transparency" => {
                self.begin_text();
                Tag::AppText(AppField::Transparency)
            }
            "textureCoordinates" => {
                self.tex_ring = a
                    .ring
                    .as_ref()
                    .map(|r| r.trim_start_matches('#').to_string());
                self.begin_text();
                Tag::TexCoords
            }
            "target" => {
                self.begin_text();
                Tag::AppTarget
            }
            _ => Tag::Plain,
        }
    }

    /// The end of a text field of a texture or material (image URI, theme, colour,
    /// transparency).
    pub(super) fn finish_app_text(&mut self, field: AppField) {
        let t = self.take_text();
        let t = t.trim();
        match field {
            AppField::ImageUri => {
                if let Some(tex) = self.textures.last_mut() {
                    tex.image_uri = t.to_string();
                }
            }
            AppField::Theme => self.app_theme = Some(t.to_string()),
            AppField::Diffuse => {
                let v: Vec<f64> = t
                    .split_whitespace()
                    .filter_map(|x| x.parse().ok())
                    .collect();
                if let (Some(m), [r, g, b]) = (self.materials.last_mut(), v.as_slice()) {
                    m.diffuse = Some([*r, *g, *b]);
                }
            }
            AppField::Transparency => {
                if let Some(m) = self.materials.last_mut() {
                    m.transparency = t.parse().ok();
                }
            }
        }
    }

    /// The end of a material's `target`.
    pub(super) fn finish_app_target(&mut self) {
        let t = self.take_text();
        let t = t.trim().trim_start_matches('#');
        if !t.is_empty()
            && self.in_material
            && let Some(m) = self.materials.last_mut()
        {
            m.targets.push(t.to_string());
        }
    }

    /// The end of `textureCoordinates`: the ring's texture coordinates (closing point removed).
    pub(super) fn finish_tex_coords(&mut self) {
        let t = self.take_text();
        let vals: Vec<f64> = t
            .split_whitespace()
            .filter_map(|x| x.parse().ok())
            .collect();
        let mut uv: Vec<[f64; 2]> = vals.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
        if uv.len() > 1 && uv.first() == uv.last() {
            uv.pop();
        }
        if let (Some(ring), Some(tex)) = (self.tex_ring.take(), self.textures.last_mut()) {
            tex.rings.insert(ring, uv);
        }
    }
}
