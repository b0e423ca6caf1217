//! Scene files mutated one value at a time: every number of a small scene with every
//! style set, replaced in turn by zero, negatives, huge, tiny and fractional values, null,
//! a string, and keys removed, must parse and render to finite layers or fail with an
//! error that says what is wrong. None may panic, which in the hosts would cross into
//! Python or Blender.

use std::panic::{catch_unwind, AssertUnwindSafe};

use crepuscular::builtin::builtin_scene;
use crepuscular::cutout::{MaskFilter, Wrap};
use crepuscular::scene::{
    AlphaMaskDesc, BasisStorage, ExactRayEnds, Extent, MaskWrapDesc, Mesh, Method, PhaseModel,
    Projection, Rectification, Scene,
};
use crepuscular::{render_scene, Error, RenderControl, Style};
use glam::Mat4;
use serde_json::Value;

/// A built-in scene cut down to a few milliseconds per render and its meshes to their
/// first 600 triangles (the files' parsing and writing cost more than the renders), with
/// every style set.
fn small_styled(name: &str, method: Method) -> Scene {
    let mut scene = builtin_scene(name).unwrap();
    scene.camera.width = 32;
    scene.camera.height = 18;
    scene.render.shadow_map_size = 64;
    scene.render.steps = 24;
    scene.render.method = method;
    scene.render.bases = 8;
    let presets = [
        include_str!("../../examples/presets/hole-filled-torus.json"),
        include_str!("../../examples/presets/extruded-colonnade.json"),
        include_str!("../../examples/presets/holes-in-tree.json"),
        include_str!("../../examples/presets/alarm.json"),
    ];
    let mut style = Style::default();
    for preset in presets {
        let preset = Style::from_json(preset).unwrap();
        style.closing = style.closing.or(preset.closing);
        style.silhouette = style.silhouette.or(preset.silhouette);
        style.holes = style.holes.or(preset.holes);
        style.tf = style.tf.or(preset.tf);
    }
    for mesh in &mut scene.meshes {
        trim(mesh, 600);
    }
    // Holes in every object but the ground.
    if let Some(holes) = style.holes.as_mut() {
        holes.objects = scene
            .meshes
            .iter()
            .map(|m| m.object_id)
            .filter(|&id| id > 1)
            .collect();
    }
    style.time = 0.5;
    scene.style = style;
    scene
}

/// Keeps the first `count` of `mesh`'s triangles and the vertices they use.
fn trim(mesh: &mut Mesh, count: usize) {
    mesh.triangles.truncate(count);
    let mut index = vec![u32::MAX; mesh.positions.len()];
    let mut kept = Vec::new();
    for triangle in &mut mesh.triangles {
        for vertex in triangle.iter_mut() {
            let slot = &mut index[*vertex as usize];
            if *slot == u32::MAX {
                *slot = kept.len() as u32;
                kept.push(mesh.positions[*vertex as usize]);
            }
            *vertex = *slot;
        }
    }
    mesh.positions = kept;
}

/// Where the mutations go: every value outside the meshes' vertex and triangle lists, and
/// in each mesh its first vertex and triangle.
fn paths(value: &Value, path: &mut Vec<String>, out: &mut Vec<String>) {
    let bulk = path.len() >= 3 && (path[2] == "positions" || path[2] == "triangles");
    match value {
        Value::Object(map) => {
            for (key, child) in map {
                path.push(key.clone());
                paths(child, path, out);
                path.pop();
            }
        }
        Value::Array(items) => {
            let shown = if bulk && path.len() == 3 {
                1
            } else {
                items.len()
            };
            for (index, child) in items.iter().take(shown).enumerate() {
                path.push(index.to_string());
                paths(child, path, out);
                path.pop();
            }
        }
        _ => {}
    }
    if !path.is_empty() {
        out.push(format!("/{}", path.join("/")));
    }
}

/// The mutated scene's outcome, or the panic's message.
fn outcome(json: &str) -> Result<Result<Vec<f32>, Error>, String> {
    catch_unwind(AssertUnwindSafe(|| {
        let scene = Scene::from_json(json)?;
        let layers = render_scene(&scene, &RenderControl::new())?;
        Ok([&layers.volume[..], &layers.visibility, &layers.depth].concat())
    }))
    .map_err(|panic| {
        panic
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default()
    })
}

fn substitutes(original: &Value) -> Vec<Option<Value>> {
    let mut out: Vec<Option<Value>> = vec![None, Some(Value::Null), Some("x".into())];
    match original {
        Value::Number(_) => out.extend(
            [0.0, -1.0, 0.5, 3.5, 1e-30, 1e30, -1e30, 4294967297.0, 1e308]
                .map(|v| Some(serde_json::json!(v))),
        ),
        Value::Array(items) => {
            out.push(Some(Value::Array(Vec::new())));
            out.push(Some(Value::Array(items[..items.len() - 1].to_vec())));
            out.push(Some(Value::Array(
                items.iter().chain(items.last()).cloned().collect(),
            )));
        }
        Value::Object(_) => out.push(Some(serde_json::json!({}))),
        Value::String(_) => out.push(Some("unknown".into())),
        Value::Bool(flag) => out.push(Some((!flag).into())),
        Value::Null => out.push(Some(serde_json::json!(1.0))),
    }
    out
}

/// Mutates every value of `scene` in turn; returns how many mutated files there were and
/// how many of them rendered.
fn mutate_every_value(scene: &Scene) -> (usize, usize) {
    // One thread per test: the renders are too small for rayon's workers to pay for
    // their waking, and the tests run side by side.
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| mutate_in_turn(scene))
}

fn mutate_in_turn(scene: &Scene) -> (usize, usize) {
    let base: Value = serde_json::from_str(&scene.to_json()).unwrap();
    let mut targets = Vec::new();
    paths(&base, &mut Vec::new(), &mut targets);
    let mut failures = Vec::new();
    let (mut tried, mut rendered) = (0, 0);
    for target in &targets {
        let original = base.pointer(target).unwrap();
        for substitute in substitutes(original) {
            let mut mutated = base.clone();
            let (parent, key) = target.rsplit_once('/').unwrap();
            let parent = mutated.pointer_mut(parent).unwrap();
            match (parent, &substitute) {
                (Value::Object(map), None) => {
                    map.remove(key);
                }
                (Value::Object(map), Some(value)) => {
                    map.insert(key.to_string(), value.clone());
                }
                (Value::Array(items), None) => {
                    items.remove(key.parse::<usize>().unwrap());
                }
                (Value::Array(items), Some(value)) => {
                    items[key.parse::<usize>().unwrap()] = value.clone();
                }
                _ => unreachable!("values sit in objects and arrays"),
            }
            let what = match &substitute {
                None => format!("{target} removed"),
                Some(value) => format!("{target} = {value}"),
            };
            tried += 1;
            let result = outcome(&mutated.to_string());
            match result {
                Err(panic) => failures.push(format!("{what}: panicked: {panic}")),
                Ok(Ok(values)) => {
                    rendered += 1;
                    if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
                        failures.push(format!("{what}: rendered {bad}"));
                    }
                }
                Ok(Err(error)) => {
                    let message = error.to_string();
                    let named = match &error {
                        Error::InvalidInput { field, .. } => !field.is_empty(),
                        _ => message.len() > 10,
                    };
                    if !named {
                        failures.push(format!("{what}: unhelpful error {message:?}"));
                    }
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    (tried, rendered)
}

/// Most mutations of a valid value are valid too: the renders ran.
fn assert_most_rendered(label: &str, (tried, rendered): (usize, usize)) {
    assert!(
        tried > 100 && rendered * 3 > tried,
        "{label}: {rendered} of {tried} mutated files rendered"
    );
}

#[test]
fn mutated_styled_scenes_render_or_say_what_is_wrong() {
    for (name, method) in [
        ("torus", Method::Prefiltered),
        ("plane", Method::MinMax),
        ("colonnade", Method::Reference),
    ] {
        assert_most_rendered(name, mutate_every_value(&small_styled(name, method)));
    }
}

#[test]
fn mutated_box_fog_and_orthographic_views_render_or_say_what_is_wrong() {
    assert_most_rendered("plane", mutate_every_value(&box_and_orthographic()));
}

/// `plane` in a box of fog seen orthographically, at half resolution, under a sun disc.
fn box_and_orthographic() -> Scene {
    let mut scene = small_styled("plane", Method::Prefiltered);
    scene.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_scale(glam::Vec3::new(8.0, 8.0, 3.0)),
    };
    scene.camera.projection = Projection::Orthographic {
        ortho_scale: 12.0,
        sensor_fit: Default::default(),
        shift_x: 0.1,
        shift_y: 0.0,
    };
    scene.render.downsample = 2;
    scene.render.sun_disc_samples = 3;
    scene.sun.angular_diameter = 0.05;
    scene
}

/// The scene options the others leave at their defaults: coloured extinction, an
/// isotropic phase, a projective rectification, supersampling, f32 basis storage, exact
/// ray ends, the near-plane correction, an alpha-masked occluder, a copy of it above that
/// casts no shadow, and a ground the camera does not see.
fn every_option(mask: &std::path::Path) -> Scene {
    let mut scene = small_styled("plane", Method::Prefiltered);
    scene.style = Style::default();
    scene.medium.channel_extinction = Some(glam::Vec3::new(0.05, 0.08, 0.12));
    scene.medium.phase = PhaseModel::Isotropic;
    scene.render.rectification = Rectification::Projective;
    scene.render.supersampling = 2;
    scene.render.basis_storage = BasisStorage::F32;
    scene.render.exact_ray_ends = ExactRayEnds::On;
    scene.render.near_plane_correction = true;
    let [ground, occluder] = &mut scene.meshes[..] else {
        panic!("plane has a ground and an occluder");
    };
    ground.seen_by_camera = false;
    occluder.uvs = Some(
        occluder
            .positions
            .iter()
            .map(|p| [p[0] * 0.1, p[1] * 0.1])
            .collect(),
    );
    occluder.alpha_mask = Some(AlphaMaskDesc {
        image: mask.to_path_buf(),
        threshold: 0.5,
        wrap: MaskWrapDesc::PerAxis([Wrap::Mirror, Wrap::Clip]),
        filter: MaskFilter::Closest,
        border: 0.25,
    });
    let mut above = occluder.clone();
    above.object_id = 3;
    above.world_from_object = Mat4::from_translation(glam::Vec3::Z) * above.world_from_object;
    above.blocks_sun = false;
    scene.meshes.push(above);
    scene
}

/// A 16² PNG whose alpha is stripes.
fn write_stripes(path: &std::path::Path) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut encoder = png::Encoder::new(file, 16, 16);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let pixels: Vec<u8> = (0..16 * 16)
        .flat_map(|i| [255, 255, 255, if (i % 16) / 4 % 2 == 0 { 255 } else { 0 }])
        .collect();
    encoder
        .write_header()
        .unwrap()
        .write_image_data(&pixels)
        .unwrap();
}

#[test]
fn mutated_scenes_of_every_option_render_or_say_what_is_wrong() {
    let folder = std::env::temp_dir().join(format!("crepuscular-mutated-{}", std::process::id()));
    std::fs::create_dir_all(&folder).unwrap();
    let mask = folder.join("stripes.png");
    write_stripes(&mask);
    let scene = every_option(&mask);
    // The mask is read: the roof's stripes let light through.
    let layers = render_scene(&scene, &RenderControl::new()).unwrap();
    let mut solid = scene.clone();
    solid.meshes.iter_mut().for_each(|m| m.alpha_mask = None);
    let solid = render_scene(&solid, &RenderControl::new()).unwrap();
    assert_ne!(layers.volume, solid.volume);
    let counts = mutate_every_value(&scene);
    std::fs::remove_dir_all(&folder).unwrap();
    assert_most_rendered("plane", counts);
}

/// Found by the mutations: an orthographic view billions of metres wide put the
/// rectified map's slice coordinates as far past its ends, and the frame planned a ray
/// for every slice index between (7 GB), or looped over billions of them.
#[test]
fn views_billions_of_metres_wide_render() {
    let mut wide = box_and_orthographic();
    wide.camera.projection = Projection::Orthographic {
        ortho_scale: 4.3e9,
        sensor_fit: Default::default(),
        shift_x: 0.1,
        shift_y: 0.0,
    };
    let mut stretched = box_and_orthographic();
    stretched.camera.world_from_camera.x_axis *= 4.3e9;
    for scene in [wide, stretched] {
        let layers = render_scene(&scene, &RenderControl::new()).unwrap();
        assert!(layers.volume.iter().all(|v| v.is_finite()));
    }
}

/// Found by the mutations: a box of fog 10³⁰ m away, which no view ray reaches, fitted the
/// shadow map to itself, and the map's matrix overflowed. The frame has no fog.
#[test]
fn a_box_of_fog_far_off_renders_no_fog() {
    let mut scene = box_and_orthographic();
    scene.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(glam::Vec3::splat(1e30)),
    };
    let layers = render_scene(&scene, &RenderControl::new()).unwrap();
    assert!(layers.volume.iter().all(|&v| v == 0.0));
    // Which the hosts name; a box in view, or of clear air, they do not.
    assert!(scene.medium.box_unreached(&layers));
    let seen = box_and_orthographic();
    let layers = render_scene(&seen, &RenderControl::new()).unwrap();
    assert!(!seen.medium.box_unreached(&layers));
    scene.medium.extinction = 0.0;
    let layers = render_scene(&scene, &RenderControl::new()).unwrap();
    assert!(!scene.medium.box_unreached(&layers));
}

/// `crepuscular render` says so when no view ray reaches the fog box, and only then.
#[test]
fn the_cli_warns_of_a_fog_box_no_view_ray_reaches() {
    let folder = std::env::temp_dir().join(format!("crepuscular-unreached-{}", std::process::id()));
    std::fs::create_dir_all(&folder).unwrap();
    let mut far = box_and_orthographic();
    far.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(glam::Vec3::splat(1e30)),
    };
    for (scene, warned) in [(box_and_orthographic(), false), (far, true)] {
        let path = folder.join("scene.json");
        std::fs::write(&path, scene.to_json()).unwrap();
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_crepuscular"))
            .arg("render")
            .arg("--scene")
            .arg(&path)
            .arg("--out")
            .arg(folder.join("out.exr"))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(output.status.success(), "{stderr}");
        assert_eq!(
            stderr.contains("no view ray reaches medium.extent's box"),
            warned,
            "{stderr}"
        );
    }
    std::fs::remove_dir_all(&folder).unwrap();
}
