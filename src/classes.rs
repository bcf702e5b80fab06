//! The evaluation class ids (`docs/design.md`) and the mapping of city-model entities onto them.
//!
//! | id | class | coarse |  | id | class | coarse |
//! |---|---|---|---|---|---|---|
//! | −1 | none | — | | 6 | tree | non-building |
//! | 0 | wall | building | | 7 | person | non-building |
//! | 1 | roof | building | | 8 | car | non-building |
//! | 2 | window | building | | 9 | road / ground | non-building |
//! | 3 | door | building | | 10 | water | non-building |
//! | 4 | ground_surface | building | | 11 | other | non-building |
//! | 5 | installation | building | | | | |
use crate::semantics::{Class, Entity};

pub const NONE: i32 = -1;
pub const WALL: i32 = 0;
pub const ROOF: i32 = 1;
pub const WINDOW: i32 = 2;
pub const DOOR: i32 = 3;
pub const GROUND_SURFACE: i32 = 4;
pub const INSTALLATION: i32 = 5;
pub const TREE: i32 = 6;
pub const PERSON: i32 = 7;
pub const CAR: i32 = 8;
pub const ROAD: i32 = 9;
pub const WATER: i32 = 10;
pub const OTHER: i32 = 11;

/// Class names indexed by id.
pub const NAMES: [&str; 12] = [
    "wall",
    "roof",
    "window",
    "door",
    "ground_surface",
    "installation",
    "tree",
    "person",
    "car",
    "road",
    "water",
    "other",
];

/// The fine-level evaluation classes of the paper.
pub const FINE: [i32; 7] = [WALL, ROOF, WINDOW, DOOR, TREE, PERSON, CAR];

/// Display colours (RGB) per class id, for overlays.
pub const PALETTE: [[u8; 3]; 12] = [
    [200, 180, 140], // wall
    [180, 60, 50],   // roof
    [60, 140, 230],  // window
    [240, 160, 40],  // door
    [120, 100, 80],  // ground_surface
    [170, 90, 200],  // installation
    [40, 160, 60],   // tree
    [250, 60, 160],  // person
    [230, 230, 30],  // car
    [90, 90, 90],    // road
    [30, 200, 220],  // water
    [255, 255, 255], // other
];

/// Colour of a class id (black for −1).
pub fn color(id: i32) -> [u8; 3] {
    usize::try_from(id)
        .ok()
        .and_then(|i| PALETTE.get(i))
        .copied()
        .unwrap_or([0, 0, 0])
}

/// The colour of Gaussians outside every building in building-coloured outputs.
pub const NO_BUILDING_COLOR: [u8; 3] = [128, 128, 128];

/// A display colour per building (its entity id `b`; [`NO_BUILDING_COLOR`] for −1): hues a
/// golden angle apart, so buildings with neighbouring ids differ clearly; saturation 0.7,
/// value 0.9.
pub fn building_color(b: i32) -> [u8; 3] {
    if b < 0 {
        return NO_BUILDING_COLOR;
    }
    let h = (f64::from(b) * 0.618_033_988_749_895).fract() * 6.0;
    let (s, v) = (0.7, 0.9);
    let c = v * s;
    let x = c * (1.0 - (h % 2.0 - 1.0).abs());
    let (r, g, bl) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r, g, bl].map(|u| ((u + m) * 255.0).round() as u8)
}

/// Name of a class id (`"none"` for −1 and unknown ids).
pub fn name(id: i32) -> &'static str {
    usize::try_from(id)
        .ok()
        .and_then(|i| NAMES.get(i))
        .copied()
        .unwrap_or("none")
}

/// Whether a class id is a building class at the coarse level (0–5).
pub fn is_building(id: i32) -> bool {
    (WALL..=INSTALLATION).contains(&id)
}

/// The class of a city-model entity: openings are windows/doors; anything under an
/// installation is an installation; surfaces by their CityGML class (ClosureSurface and
/// OuterCeilingSurface count as wall, OuterFloorSurface as roof: it faces the sky); building
/// geometry without a thematic surface counts as wall.
pub fn of_entity(entities: &[Entity], id: i32) -> i32 {
    let Some(e) = usize::try_from(id).ok().and_then(|i| entities.get(i)) else {
        return NONE;
    };
    if e.class.is_window() {
        return WINDOW;
    }
    if e.class.is_door() {
        return DOOR;
    }
    // At most one step per entity: a parent cycle (a damaged table) cannot hang the walk.
    let mut cur = Some(e);
    for _ in 0..=entities.len() {
        let Some(x) = cur else { break };
        if x.class.is_installation() {
            return INSTALLATION;
        }
        cur = x.parent.and_then(|p| entities.get(p as usize));
    }
    match e.class {
        Class::RoofSurface | Class::OuterFloorSurface => ROOF,
        Class::GroundSurface => GROUND_SURFACE,
        _ => WALL,
    }
}

/// [`of_entity`] for every entity, indexed by entity id.
pub fn table(entities: &[Entity]) -> Vec<i32> {
    (0..entities.len() as i32)
        .map(|i| of_entity(entities, i))
        .collect()
}

/// The class prompts of the pipeline's text queries and of `gs4city features`' `prompts.json`,
/// each with the class it targets (`None` = "a building", no single class: counted as a wall,
/// a building prompt). The simulator (`synth`) places its simulated prompt vectors by them.
pub const CLASS_PROMPTS: [(&str, Option<i32>); 14] = [
    ("a wall of a building", Some(WALL)),
    ("a facade of a building", Some(WALL)),
    ("a roof", Some(ROOF)),
    ("a window of a building", Some(WINDOW)),
    ("a door", Some(DOOR)),
    ("the ground surface of a building", Some(GROUND_SURFACE)),
    ("a balcony of a building", Some(INSTALLATION)),
    ("a tree", Some(TREE)),
    ("a person", Some(PERSON)),
    ("a car", Some(CAR)),
    ("a road", Some(ROAD)),
    ("water", Some(WATER)),
    ("the sky", Some(NONE)),
    ("a building", None),
];

/// A semantic network's class set mapped onto the evaluation classes (`gs4city segment
/// --semantic`, docs/segment.md): `(name, class)`, `None` = no class (no mask is made of it).
/// Sky is class −1 (`NONE`): masks are made of it (the features test puts class −1 in neither
/// prompt set); a name that is no city part, ground, water, tree, person or vehicle is
/// `OTHER` (11), a foreground object.
pub type ClassTable = &'static [(&'static str, Option<i32>)];

/// Cityscapes' 19 evaluation classes in their train-id order, then `void` (unlabelled):
/// building and wall → wall (the building class), road, sidewalk and terrain → road/ground,
/// vegetation → tree, person and rider → person, the vehicles with an engine → car, fence,
/// pole, traffic light and sign, bicycle → other, sky → −1, void → none.
pub const CITYSCAPES: [(&str, Option<i32>); 20] = [
    ("road", Some(ROAD)),
    ("sidewalk", Some(ROAD)),
    ("building", Some(WALL)),
    ("wall", Some(WALL)),
    ("fence", Some(OTHER)),
    ("pole", Some(OTHER)),
    ("traffic light", Some(OTHER)),
    ("traffic sign", Some(OTHER)),
    ("vegetation", Some(TREE)),
    ("terrain", Some(ROAD)),
    ("sky", Some(NONE)),
    ("person", Some(PERSON)),
    ("rider", Some(PERSON)),
    ("car", Some(CAR)),
    ("truck", Some(CAR)),
    ("bus", Some(CAR)),
    ("train", Some(CAR)),
    ("motorcycle", Some(CAR)),
    ("bicycle", Some(OTHER)),
    ("void", None),
];

/// ADE20K's 150 classes (SceneParsing, `objectInfo150` order): buildings (wall, building,
/// house, skyscraper, hovel, tower) → wall, windowpane → window, doors → door, awning,
/// canopy, railing, bannister, column, stairs, stairway, step → installation, tree, plant,
/// palm, flower → tree, person → person, car, bus, truck, van, minibike → car, ground stuff
/// (road, sidewalk, floor, earth, grass, field, sand, path, runway, dirt track, land, rock,
/// mountain, hill) → road/ground, water bodies → water, sky → −1, the rest (furniture, objects)
/// → other.
pub const ADE20K: [(&str, Option<i32>); 150] = [
    ("wall", Some(WALL)),
    ("building", Some(WALL)),
    ("sky", Some(NONE)),
    ("floor", Some(ROAD)),
    ("tree", Some(TREE)),
    ("ceiling", Some(OTHER)),
    ("road", Some(ROAD)),
    ("bed", Some(OTHER)),
    ("windowpane", Some(WINDOW)),
    ("grass", Some(ROAD)),
    ("cabinet", Some(OTHER)),
    ("sidewalk", Some(ROAD)),
    ("person", Some(PERSON)),
    ("earth", Some(ROAD)),
    ("door", Some(DOOR)),
    ("table", Some(OTHER)),
    ("mountain", Some(ROAD)),
    ("plant", Some(TREE)),
    ("curtain", Some(OTHER)),
    ("chair", Some(OTHER)),
    ("car", Some(CAR)),
    ("water", Some(WATER)),
    ("painting", Some(OTHER)),
    ("sofa", Some(OTHER)),
    ("shelf", Some(OTHER)),
    ("house", Some(WALL)),
    ("sea", Some(WATER)),
    ("mirror", Some(OTHER)),
    ("rug", Some(OTHER)),
    ("field", Some(ROAD)),
    ("armchair", Some(OTHER)),
    ("seat", Some(OTHER)),
    ("fence", Some(OTHER)),
    ("desk", Some(OTHER)),
    ("rock", Some(ROAD)),
    ("wardrobe", Some(OTHER)),
    ("lamp", Some(OTHER)),
    ("bathtub", Some(OTHER)),
    ("railing", Some(INSTALLATION)),
    ("cushion", Some(OTHER)),
    ("base", Some(OTHER)),
    ("box", Some(OTHER)),
    ("column", Some(INSTALLATION)),
    ("signboard", Some(OTHER)),
    ("chest of drawers", Some(OTHER)),
    ("counter", Some(OTHER)),
    ("sand", Some(ROAD)),
    ("sink", Some(OTHER)),
    ("skyscraper", Some(WALL)),
    ("fireplace", Some(OTHER)),
    ("refrigerator", Some(OTHER)),
    ("grandstand", Some(OTHER)),
    ("path", Some(ROAD)),
    ("stairs", Some(INSTALLATION)),
    ("runway", Some(ROAD)),
    ("case", Some(OTHER)),
    ("pool table", Some(OTHER)),
    ("pillow", Some(OTHER)),
    ("screen door", Some(DOOR)),
    ("stairway", Some(INSTALLATION)),
    ("river", Some(WATER)),
    ("bridge", Some(OTHER)),
    ("bookcase", Some(OTHER)),
    ("blind", Some(OTHER)),
    ("coffee table", Some(OTHER)),
    ("toilet", Some(OTHER)),
    ("flower", Some(TREE)),
    ("book", Some(OTHER)),
    ("hill", Some(ROAD)),
    ("bench", Some(OTHER)),
    ("countertop", Some(OTHER)),
    ("stove", Some(OTHER)),
    ("palm", Some(TREE)),
    ("kitchen island", Some(OTHER)),
    ("computer", Some(OTHER)),
    ("swivel chair", Some(OTHER)),
    ("boat", Some(OTHER)),
    ("bar", Some(OTHER)),
    ("arcade machine", Some(OTHER)),
    ("hovel", Some(WALL)),
    ("bus", Some(CAR)),
    ("towel", Some(OTHER)),
    ("light", Some(OTHER)),
    ("truck", Some(CAR)),
    ("tower", Some(WALL)),
    ("chandelier", Some(OTHER)),
    ("awning", Some(INSTALLATION)),
    ("streetlight", Some(OTHER)),
    ("booth", Some(OTHER)),
    ("television receiver", Some(OTHER)),
    ("airplane", Some(OTHER)),
    ("dirt track", Some(ROAD)),
    ("apparel", Some(OTHER)),
    ("pole", Some(OTHER)),
    ("land", Some(ROAD)),
    ("bannister", Some(INSTALLATION)),
    ("escalator", Some(OTHER)),
    ("ottoman", Some(OTHER)),
    ("bottle", Some(OTHER)),
    ("buffet", Some(OTHER)),
    ("poster", Some(OTHER)),
    ("stage", Some(OTHER)),
    ("van", Some(CAR)),
    ("ship", Some(OTHER)),
    ("fountain", Some(WATER)),
    ("conveyer belt", Some(OTHER)),
    ("canopy", Some(INSTALLATION)),
    ("washer", Some(OTHER)),
    ("plaything", Some(OTHER)),
    ("swimming pool", Some(WATER)),
    ("stool", Some(OTHER)),
    ("barrel", Some(OTHER)),
    ("basket", Some(OTHER)),
    ("waterfall", Some(WATER)),
    ("tent", Some(OTHER)),
    ("bag", Some(OTHER)),
    ("minibike", Some(CAR)),
    ("cradle", Some(OTHER)),
    ("oven", Some(OTHER)),
    ("ball", Some(OTHER)),
    ("food", Some(OTHER)),
    ("step", Some(INSTALLATION)),
    ("tank", Some(OTHER)),
    ("trade name", Some(OTHER)),
    ("microwave", Some(OTHER)),
    ("pot", Some(OTHER)),
    ("animal", Some(OTHER)),
    ("bicycle", Some(OTHER)),
    ("lake", Some(WATER)),
    ("dishwasher", Some(OTHER)),
    ("screen", Some(OTHER)),
    ("blanket", Some(OTHER)),
    ("sculpture", Some(OTHER)),
    ("hood", Some(OTHER)),
    ("sconce", Some(OTHER)),
    ("vase", Some(OTHER)),
    ("traffic light", Some(OTHER)),
    ("tray", Some(OTHER)),
    ("ashcan", Some(OTHER)),
    ("fan", Some(OTHER)),
    ("pier", Some(OTHER)),
    ("crt screen", Some(OTHER)),
    ("plate", Some(OTHER)),
    ("monitor", Some(OTHER)),
    ("bulletin board", Some(OTHER)),
    ("shower", Some(OTHER)),
    ("radiator", Some(OTHER)),
    ("glass", Some(OTHER)),
    ("clock", Some(OTHER)),
    ("flag", Some(OTHER)),
];

/// The class table called `name` (`cityscapes`, `ade20k`; case-insensitive).
pub fn class_table(name: &str) -> Option<ClassTable> {
    match name.to_ascii_lowercase().as_str() {
        "cityscapes" => Some(&CITYSCAPES),
        "ade20k" => Some(&ADE20K),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::citygml::Level;

    fn e(id: i32, class: &str, parent: Option<i32>) -> Entity {
        Entity {
            id,
            object_id: format!("e{id}"),
            class: Class::from_local_name(class).unwrap(),
            level: Level::Feature,
            parent,
            building: 0,
            source: String::new(),
            lod: Some(3),
            attributes: Default::default(),
        }
    }

    #[test]
    fn entity_classes() {
        let es = vec![
            e(0, "Building", None),
            e(1, "WallSurface", Some(0)),
            e(2, "Window", Some(1)),
            e(3, "BuildingInstallation", Some(0)),
            e(4, "RoofSurface", Some(3)),
            e(5, "OuterFloorSurface", Some(0)),
            e(6, "DoorSurface", Some(1)),
        ];
        assert_eq!(
            table(&es),
            vec![WALL, WALL, WINDOW, INSTALLATION, INSTALLATION, ROOF, DOOR]
        );
        assert_eq!(of_entity(&es, 99), NONE);
        assert_eq!(name(CAR), "car");
        assert_eq!(name(-1), "none");
        assert!(is_building(INSTALLATION) && !is_building(TREE));
    }
}
