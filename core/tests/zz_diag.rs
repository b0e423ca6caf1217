// scratch: dump the sideways views as JSON scenes
use crepuscular::builtin_scene;
use crepuscular::scene::Camera;
use glam::Vec3;
#[test]
fn dump() {
    for name in ["plane", "colonnade"] {
        let scene = builtin_scene(name).unwrap();
        let eye = scene.camera.world_from_camera.w_axis.truncate();
        let towards_sun = -scene.sun.direction.normalize();
        let side = Vec3::new(-towards_sun.y, towards_sun.x, -0.15).normalize();
        let side_view = Camera::pinhole_looking_at(eye, eye + side, 24.0, 192, 108);
        let mut s = scene.clone();
        s.camera = side_view;
        std::fs::write(
            format!("/tmp/{name}_sideways.json"),
            serde_json::to_string_pretty(&s).unwrap(),
        )
        .unwrap();
        let mut d = scene.clone();
        d.camera.width = 192;
        d.camera.height = 108;
        std::fs::write(
            format!("/tmp/{name}_default.json"),
            serde_json::to_string_pretty(&d).unwrap(),
        )
        .unwrap();
    }
}
