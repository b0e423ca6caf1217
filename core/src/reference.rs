//! Brute-force single scattering: the reference every faster method is measured against.
//!
//! Each view ray is marched in uniform steps. Visibility is sampled once per step (it is
//! piecewise constant), and the transmittance inside a step is integrated in closed form,
//! so that with no occluders the result is exact for any step count.

use std::cell::Cell;

use glam::{DMat4, DVec3};

use crate::camera::Ray;
use crate::scene::{Extent, Medium, Sun};
use crate::shadow_map::ShadowMap;
use crate::spans::JoinedSpans;

/// What one view ray contributes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RaySample {
    /// In-scattered radiance per unit of σs·E: multiply by albedo · σt · E for RGB.
    pub scattering: f64,
    /// 1 − transmittance through the medium along the ray.
    pub alpha: f64,
    /// Average sun visibility along the ray segment.
    pub visibility: f64,
}

impl RaySample {
    /// An empty stretch of medium: nothing scattered or absorbed, nothing shadowed.
    pub const EMPTY: RaySample = RaySample {
        scattering: 0.0,
        alpha: 0.0,
        visibility: 1.0,
    };
}

/// The part of [t_start, t_end] where the ray is inside the medium: all of it when the
/// medium is unbounded, `None` when the ray misses the box.
pub(crate) fn medium_segment(
    box_medium: Option<&BoxMedium>,
    ray: &Ray,
    t_start: f64,
    t_end: f64,
) -> Option<(f64, f64)> {
    match box_medium {
        None => Some((t_start, t_end)),
        Some(box_medium) => box_medium
            .clip(ray)
            .map(|(a, b)| (a.max(t_start), b.min(t_end)))
            .filter(|(a, b)| b > a),
    }
}

/// ∫ e^(−σ·(ℓ(t) + t − a)) dt over [p, q], where the sunward depth ℓ runs linearly from
/// `depths` [ℓ(p), ℓ(q)] with slope `beta`. The exponent is taken at the stretch's lighter
/// end: where ℓ falls faster than t rises, from the far end, so that e^(−σ·…) and the
/// integral never meet as 0 · ∞. A sun grazing a wall by 10⁻²⁵ gives a line of slope 10²⁵,
/// and fog of 1000 /m a step's slope of −2 an exponent of 2000 over a metre: either read
/// 0 · ∞ = NaN from the near end.
fn stretch_integral(sigma: f64, a: f64, [p, q]: [f64; 2], depths: [f64; 2], beta: f64) -> f64 {
    let k = sigma * (1.0 + beta);
    if k >= 0.0 {
        (-sigma * (depths[0] + p - a)).exp() * integral_exp(k, q - p)
    } else {
        (-sigma * (depths[1] + q - a)).exp() * integral_exp(-k, q - p)
    }
}

/// ∫₀ᵈ e^(−k·u) du, also for k near zero or negative.
pub fn integral_exp(k: f64, d: f64) -> f64 {
    let kd = k * d;
    if kd.abs() < 1e-8 {
        d * (1.0 - 0.5 * kd)
    } else {
        -(-kd).exp_m1() / k
    }
}

/// The medium's box in the form ray marching needs.
#[derive(Clone, Copy, Debug)]
pub(crate) struct BoxMedium {
    cube_from_world: DMat4,
    /// Direction towards the sun, in cube coordinates but per world unit; `None` where the
    /// sunlight is not attenuated in the box ([`Sun::attenuated_by_medium`]): its sunward
    /// depth is 0 everywhere.
    towards_sun: Option<DVec3>,
}

impl BoxMedium {
    pub(crate) fn new(extent: &Extent, sun: &Sun) -> Option<Self> {
        let light_travel = sun.direction.as_dvec3().normalize();
        Self::lit_along(extent, light_travel, sun.attenuated_by_medium)
    }

    fn lit_along(extent: &Extent, light_travel: DVec3, attenuated: bool) -> Option<Self> {
        match extent {
            Extent::Unbounded => None,
            Extent::Box { world_from_cube } => {
                let cube_from_world = world_from_cube.as_dmat4().inverse();
                Some(BoxMedium {
                    cube_from_world,
                    towards_sun: attenuated
                        .then(|| cube_from_world.transform_vector3(-light_travel)),
                })
            }
        }
    }

    /// What integrating along `ray` needs, once per ray.
    pub(crate) fn along(&self, ray: &Ray) -> BoxRay {
        let Some(towards_sun) = self.towards_sun else {
            // ℓ = 0: one line, and the others never lower.
            let flat = (0.0, 0.0);
            let never = (f64::INFINITY, 0.0);
            return BoxRay {
                lines: [flat, never, never],
            };
        };
        let origin = self.cube_from_world.transform_point3(ray.origin);
        let direction = self.cube_from_world.transform_vector3(ray.direction);
        let mut lines = [(f64::INFINITY, 0.0); 3];
        for (axis, line) in lines.iter_mut().enumerate() {
            let s = towards_sun[axis];
            if s != 0.0 {
                let wall = if s > 0.0 { 1.0 } else { -1.0 };
                *line = ((wall - origin[axis]) / s, -direction[axis] / s);
            }
        }
        BoxRay { lines }
    }

    /// Parameter range where the ray is inside the box, if any.
    pub(crate) fn clip(&self, ray: &Ray) -> Option<(f64, f64)> {
        let origin = self.cube_from_world.transform_point3(ray.origin);
        let direction = self.cube_from_world.transform_vector3(ray.direction);
        let mut near = f64::NEG_INFINITY;
        let mut far = f64::INFINITY;
        for axis in 0..3 {
            let (o, d) = (origin[axis], direction[axis]);
            if d.abs() < 1e-300 {
                if o.abs() > 1.0 {
                    return None;
                }
                continue;
            }
            let (t0, t1) = ((-1.0 - o) / d, (1.0 - o) / d);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        (near < far).then_some((near, far))
    }

    /// Distance from a cube-space point to the box boundary, towards the sun.
    #[inline]
    fn sunward_depth(&self, cube_point: DVec3) -> f64 {
        let Some(towards_sun) = self.towards_sun else {
            return 0.0;
        };
        let mut depth = f64::INFINITY;
        for axis in 0..3 {
            let s = towards_sun[axis];
            if s != 0.0 {
                let wall = if s > 0.0 { 1.0 } else { -1.0 };
                depth = depth.min((wall - cube_point[axis]) / s);
            }
        }
        depth.max(0.0)
    }
}

/// Share of a ray's stretch below which [`BoxRay::sunward_change`] ignores a part.
pub(crate) const NEGLIGIBLE_STRETCH: f64 = 1e-3;

/// One ray's sunward depth inside a box: ℓ(t) = min over the walls the sun direction
/// points at of α_j + β_j·t.
#[derive(Clone, Copy, Debug)]
pub(crate) struct BoxRay {
    lines: [(f64, f64); 3],
}

impl BoxRay {
    /// Calls `visit(p, q, α, β)` for each stretch [p, q] of [t0, t1] over which ℓ is one
    /// line, α + β·t: ℓ is the minimum of three linear functions of t, so it is linear
    /// between the points where the minimum switches.
    ///
    /// Each stretch takes the line lowest at its middle, not the minimum at its ends. A
    /// wall the sun grazes has a nearly vertical line (torus's sun has an x component of
    /// −2·10⁻¹⁷, rounding's, and in a box aligned with the axes the line of its x wall rose
    /// 10¹⁶ m per m): it is lowest only within rounding of where the ray crosses that wall,
    /// but at the ray's entry through it the minimum at the end was about 0, and a stretch
    /// interpolated from there read the fog up to twice as bright.
    fn for_each_line(&self, t0: f64, t1: f64, mut visit: impl FnMut(f64, f64, f64, f64)) {
        let lines = &self.lines;
        let mut cuts = [t0, t1, t1, t1, t1];
        let mut count = 1;
        for i in 0..3 {
            for j in i + 1..3 {
                let ((ai, bi), (aj, bj)) = (lines[i], lines[j]);
                if ai.is_finite() && aj.is_finite() && bi != bj {
                    let t = (aj - ai) / (bi - bj);
                    if t > t0 && t < t1 {
                        cuts[count] = t;
                        count += 1;
                    }
                }
            }
        }
        cuts[count] = t1;
        cuts[..=count].sort_by(f64::total_cmp);
        for piece in cuts[..=count].windows(2) {
            let (p, q) = (piece[0], piece[1]);
            if q > p {
                let middle = 0.5 * (p + q);
                let (alpha, beta) = lines
                    .iter()
                    .copied()
                    .min_by(|x, y| (x.0 + x.1 * middle).total_cmp(&(y.0 + y.1 * middle)))
                    .unwrap_or((f64::INFINITY, 0.0));
                visit(p, q, alpha, beta);
            }
        }
    }

    /// ∫ e^(−σ·ℓ(t)) · e^(−σ·(t − a)) dt over [t0, t1] inside the box, exactly.
    pub(crate) fn integrate(&self, t0: f64, t1: f64, a: f64, sigma: f64) -> f64 {
        let mut total = 0.0;
        self.for_each_line(t0, t1, |p, q, alpha, beta| {
            let depth = |t: f64| (alpha + beta * t).max(0.0);
            total += stretch_integral(sigma, a, [p, q], [depth(p), depth(q)], beta);
        });
        total
    }

    /// How far the sunward depth ℓ rises and falls over [t0, t1], in all, leaving out
    /// stretches shorter than [`NEGLIGIBLE_STRETCH`] of it: near a wall the sun grazes, ℓ
    /// jumps from 0 to the other walls' depth within rounding of the wall, and such a jump
    /// weighs nothing in any integral along the ray.
    pub(crate) fn sunward_change(&self, t0: f64, t1: f64) -> f64 {
        let shortest = NEGLIGIBLE_STRETCH * (t1 - t0);
        let mut change = 0.0;
        self.for_each_line(t0, t1, |p, q, _, beta| {
            if q - p > shortest {
                change += beta.abs() * (q - p);
            }
        });
        change
    }
}

/// V̄ of a ray: its in-scattering over what it would be unshadowed, i.e. visibility
/// averaged along the ray with the weights light actually reaches the camera with. It is
/// the plain average in thin media, and `None` where no medium is crossed.
pub(crate) fn weighted_visibility(scattering: f64, unshadowed: f64) -> Option<f64> {
    (unshadowed > 1e-300).then(|| (scattering / unshadowed).clamp(0.0, 1.0))
}

/// Where a walk may stop ([`Marcher::lit_spans`]): past `enough` unless `dark` says the
/// light seen so far (as far as the lit parts already handed on) is too little to
/// neglect the rest, and past `farthest` in any case.
pub(crate) struct WalkEnd<D> {
    enough: f64,
    farthest: f64,
    dark: D,
}

impl WalkEnd<fn(f64) -> bool> {
    /// A walk to the end of its stretch.
    const NEVER: Self = Self {
        enough: f64::INFINITY,
        farthest: f64::INFINITY,
        dark: |_| false,
    };
}

impl<D: Fn(f64) -> bool> WalkEnd<D> {
    /// A walk from `origin` in a medium of extinction `sigma`: it may stop at
    /// [`WALK_DEPTH`], or, with `dark_walks`, where `dark(t)` holds at [`DARK_WALK_DEPTH`].
    fn at(origin: f64, sigma: f64, dark_walks: bool, dark: D) -> Self {
        let enough = origin + WALK_DEPTH / sigma;
        Self {
            enough,
            farthest: if dark_walks {
                origin + DARK_WALK_DEPTH / sigma
            } else {
                enough
            },
            dark,
        }
    }

    /// Whether the walk stops on leaving a texel at `t`.
    #[inline]
    fn ends_at(&self, t: f64) -> bool {
        t > self.farthest || (t > self.enough && !(self.dark)(t))
    }
}

/// Optical depth along a ray after which [`Marcher::walk_texels`] stops: the rest could
/// add at most e^−10 (4.5·10⁻⁵) of the ray's unshadowed light, two orders below the fast
/// methods' errors. In dense fog the fast methods walk most rays
/// ([`crate::epipolar::LOOKUP_DEPTH`]), and walking to e^−20 made frames at σ = 1.5 /m
/// 1.4–1.9× slower than this.
pub const WALK_DEPTH: f64 = 10.0;

/// In a nearly dark frame ([`Marcher::with_dark_walks`]), a walk that has seen less than
/// this share of its unshadowed light by [`WALK_DEPTH`] goes on to [`DARK_WALK_DEPTH`]:
/// what it sees may be less than what lies past e^−10. In a nearly black view (`plane` in
/// fog of 0.6 /m under a dilated silhouette, visibility 6·10⁻⁵) the light past it was a
/// third of the frame's, which prefiltering read 14% dark. In every frame it took dense
/// fog 1.4–2.6× as long (`bench --extinction 1.5`), since most of its rays see no light.
pub const DARK_WALK_SHARE: f64 = 0.01;

/// Optical depth where a walk still dark by [`WALK_DEPTH`] stops: the rest adds at most
/// e^−20 (2·10⁻⁹) of its unshadowed light.
pub const DARK_WALK_DEPTH: f64 = 20.0;

/// Per-frame constants of the march.
#[derive(Clone, Debug)]
pub struct Marcher<'a> {
    shadow: &'a ShadowMap,
    extinction: f64,
    steps: u32,
    box_medium: Option<BoxMedium>,
    /// Walks still dark at e^−10 go on ([`DARK_WALK_SHARE`]).
    dark_walks: bool,
}

impl<'a> Marcher<'a> {
    pub fn new(shadow: &'a ShadowMap, sun: &Sun, medium: &Medium, steps: u32) -> Self {
        Self {
            shadow,
            extinction: medium.extinction as f64,
            steps,
            box_medium: BoxMedium::new(&medium.extent, sun),
            dark_walks: false,
        }
    }

    /// This marcher with walks that go on past e^−10 while they have seen less than
    /// [`DARK_WALK_SHARE`] of their light: for a nearly dark frame, whose own light is of
    /// the order of what a walk leaves out there.
    pub fn with_dark_walks(self, dark_walks: bool) -> Self {
        Self { dark_walks, ..self }
    }

    /// Whether the medium fills a box rather than all space.
    pub fn in_box(&self) -> bool {
        self.box_medium.is_some()
    }

    /// In a `box` medium, 1 − transmittance along the ray over [t_start, t_end], the
    /// opacity every method gives it; `None` in an unbounded one.
    pub fn box_opacity(&self, ray: &Ray, t_start: f64, t_end: f64) -> Option<f64> {
        let box_medium = self.box_medium.as_ref()?;
        Some(
            medium_segment(Some(box_medium), ray, t_start, t_end)
                .map_or(0.0, |(a, b)| -(-self.extinction * (b - a)).exp_m1()),
        )
    }

    /// The shadow map the marcher reads.
    pub fn shadow(&self) -> &'a ShadowMap {
        self.shadow
    }

    /// The opacity and visibility of a ray from `t_start` to `t_end` whose light ends at
    /// `lit_end` ([`crate::shadowed_end`]), from the `visibility` of its stretch to
    /// `lit_end`: the opacity of the whole ray, and the visibility averaged over all of it
    /// with the same weights, the stretch past `lit_end` dark.
    pub(crate) fn dark_tail(
        &self,
        ray: &Ray,
        t_start: f64,
        lit_end: f64,
        t_end: f64,
        visibility: f64,
    ) -> (f64, f64) {
        let sigma = self.extinction;
        let (alpha, lit_weight, weight) = match &self.box_medium {
            None => (
                -(-sigma * (t_end - t_start)).exp_m1(),
                integral_exp(sigma, lit_end - t_start),
                integral_exp(sigma, t_end - t_start),
            ),
            Some(box_medium) => match medium_segment(Some(box_medium), ray, t_start, t_end) {
                None => (0.0, 0.0, 0.0),
                Some((a, b)) => {
                    let along = box_medium.along(ray);
                    let lit_weight = if lit_end > a {
                        along.integrate(a, lit_end.min(b), a, sigma)
                    } else {
                        0.0
                    };
                    (
                        -(-sigma * (b - a)).exp_m1(),
                        lit_weight,
                        along.integrate(a, b, a, sigma),
                    )
                }
            },
        };
        let share = if weight > 1e-300 {
            lit_weight / weight
        } else {
            (lit_end - t_start) / (t_end - t_start)
        };
        (alpha, (visibility * share).clamp(0.0, 1.0))
    }

    /// Integrates one ray over [t_start, t_end].
    pub fn march(&self, ray: &Ray, t_start: f64, t_end: f64) -> RaySample {
        self.march_in_steps(ray, t_start, t_end, self.steps)
    }

    /// A fast method's fallback for rays near an epipole and rays it declines, which
    /// cross few shadow-map texels: the ray is walked texel by texel and integrated
    /// exactly, the limit the march tends to as its steps grow, at a cost of one lookup
    /// per texel crossed ([`Marcher::walk_texels`]; in a `box` medium only the stretch
    /// inside the box, each lit part attenuated through it).
    pub fn march_fallback(&self, ray: &Ray, t_start: f64, t_end: f64) -> RaySample {
        match &self.box_medium {
            None => self.walk_texels(ray, t_start, t_end),
            Some(box_medium) => self.walk_box(box_medium, ray, t_start, t_end),
        }
    }

    /// Exact single scattering along a ray outside any box: a 2D walk through the shadow
    /// map's texels, each crossing's lit part found where the ray's light depth meets the
    /// texel's occluder (`ShadowMap::is_lit`), and its in-scattering integrated in closed
    /// form.
    pub fn walk_texels(&self, ray: &Ray, t_start: f64, t_end: f64) -> RaySample {
        if t_end <= t_start {
            return RaySample::EMPTY;
        }
        let sigma = self.extinction;
        let scattering = Cell::new(0.0);
        let walk = WalkEnd::at(t_start, sigma, self.dark_walks, |t| {
            scattering.get() < DARK_WALK_SHARE * integral_exp(sigma, t - t_start)
        });
        self.lit_spans(ray, t_start, t_end, walk, |a, b| {
            let lit = (-sigma * (a - t_start)).exp() * integral_exp(sigma, b - a);
            scattering.set(scattering.get() + lit);
        });
        let scattering = scattering.get();
        // One exponential for both the opacity and the unshadowed in-scattering.
        let depth = sigma * (t_end - t_start);
        let transmittance_m1 = (-depth).exp_m1();
        let unshadowed = if depth.abs() < 1e-8 {
            integral_exp(sigma, t_end - t_start)
        } else {
            -transmittance_m1 / sigma
        };
        RaySample {
            scattering,
            alpha: -transmittance_m1,
            visibility: (scattering / unshadowed).clamp(0.0, 1.0),
        }
    }

    /// [`Marcher::walk_texels`] in a `box` medium: only the stretch inside the box is
    /// walked, each lit part integrated with the sunlight's attenuation through the box
    /// ([`BoxRay::integrate`]). A ray that misses the box gets the plain fraction of it
    /// that is lit, as the march gives it.
    pub(crate) fn walk_box(
        &self,
        box_medium: &BoxMedium,
        ray: &Ray,
        t_start: f64,
        t_end: f64,
    ) -> RaySample {
        if t_end <= t_start {
            return RaySample::EMPTY;
        }
        let lit_fraction = || {
            let mut lit = 0.0;
            self.lit_spans(ray, t_start, t_end, WalkEnd::NEVER, |a, b| lit += b - a);
            lit / (t_end - t_start)
        };
        let Some((a, b)) = medium_segment(Some(box_medium), ray, t_start, t_end) else {
            return RaySample {
                visibility: lit_fraction(),
                ..RaySample::EMPTY
            };
        };
        let sigma = self.extinction;
        let along = box_medium.along(ray);
        let scattering = Cell::new(0.0);
        let walk = WalkEnd::at(a, sigma, self.dark_walks, |t| {
            scattering.get() < DARK_WALK_SHARE * along.integrate(a, t, a, sigma)
        });
        self.lit_spans(ray, a, b, walk, |t0, t1| {
            scattering.set(scattering.get() + along.integrate(t0, t1, a, sigma));
        });
        let scattering = scattering.get();
        let unshadowed = along.integrate(a, b, a, sigma);
        RaySample {
            scattering,
            alpha: -(-sigma * (b - a)).exp_m1(),
            visibility: weighted_visibility(scattering, unshadowed).unwrap_or_else(lit_fraction),
        }
    }

    /// Calls `lit` with each lit part [t0, t1] of the ray within [`t_start`, `t_end`], in
    /// order, walking the shadow map's texels; the walk stops where `walk` says the rest
    /// adds nothing that matters. Off the map counts as lit. Lit parts in consecutive
    /// texels are joined into one call: each call integrates in closed form, with an
    /// exponential or two, and a mostly lit ray crosses hundreds of texels.
    fn lit_spans(
        &self,
        ray: &Ray,
        t_start: f64,
        t_end: f64,
        walk: WalkEnd<impl Fn(f64) -> bool>,
        mut lit: impl FnMut(f64, f64),
    ) {
        let shadow = self.shadow;
        let origin = shadow.texel_from_world.transform_point3(ray.origin);
        let step = shadow.texel_from_world.transform_vector3(ray.direction);
        let size = shadow.size as i64;
        let at = |t: f64| origin + step * t;
        let start = at(t_start);
        let mut cell = [start.x.floor() as i64, start.y.floor() as i64];
        // Per axis: the t of the next cell border, the t between borders, the cell step.
        let axis = |o: f64, d: f64, c: i64| {
            if d > 0.0 {
                ((c + 1) as f64 - o) / d
            } else if d < 0.0 {
                (c as f64 - o) / d
            } else {
                f64::INFINITY
            }
        };
        let (mut next_x, mut next_y) = (
            axis(origin.x, step.x, cell[0]),
            axis(origin.y, step.y, cell[1]),
        );
        // Each axis in variables of its own: from arrays indexed by the axis stepped, the
        // compiler divided again for the t between borders at every texel.
        let (delta_x, delta_y) = (1.0 / step.x.abs(), 1.0 / step.y.abs());
        let (direction_x, direction_y) = (step.x.signum() as i64, step.y.signum() as i64);
        let end = at(t_end);
        let cells = (end.x - start.x).abs().ceil() + (end.y - start.y).abs().ceil() + 2.0;
        // Lit while origin.z + step.z·t ≤ threshold: the part of [t, exit] before or after
        // the ray meets the threshold, by a multiplication rather than a division a texel.
        // Comparisons rather than f64::min and max, whose NaN handling lengthened each
        // step's chain of dependent operations: a NaN meet (no threshold) leaves the part
        // lit, as they did.
        let per_z = 1.0 / step.z;
        let lit_part = |threshold: f64, t: f64, exit: f64| {
            let meet = (threshold - origin.z) * per_z;
            if step.z > 0.0 {
                (t, if meet < exit { meet } else { exit })
            } else if step.z < 0.0 {
                (if meet > t { meet } else { t }, exit)
            } else if origin.z <= threshold {
                (t, exit)
            } else {
                (t, t)
            }
        };
        let mut t = t_start;
        let mut spans = JoinedSpans::default();
        for _ in 0..cells.min(1e7) as usize {
            let along_y = next_y < next_x;
            let border = if along_y { next_y } else { next_x };
            let exit = if border < t_end { border } else { t_end };
            let exit = if exit > t { exit } else { t };
            let inside = (0..size).contains(&cell[0]) && (0..size).contains(&cell[1]);
            let (lit_from, lit_to) = if !inside {
                (t, exit)
            } else {
                let texel = shadow.depth[(cell[1] * size + cell[0]) as usize];
                lit_part(texel as f64 + shadow.bias, t, exit)
            };
            spans.push(lit_from, lit_to, &mut lit);
            if exit >= t_end || walk.ends_at(exit) {
                break;
            }
            cell[0] += if along_y { 0 } else { direction_x };
            cell[1] += if along_y { direction_y } else { 0 };
            next_x += if along_y { 0.0 } else { delta_x };
            next_y += if along_y { delta_y } else { 0.0 };
            t = exit;
        }
        spans.finish(&mut lit);
    }

    fn march_in_steps(&self, ray: &Ray, t_start: f64, t_end: f64, steps: u32) -> RaySample {
        if t_end <= t_start {
            return RaySample::EMPTY;
        }
        let texel_origin = self.shadow.texel_from_world.transform_point3(ray.origin);
        let texel_step = self
            .shadow
            .texel_from_world
            .transform_vector3(ray.direction);
        let lit = |t: f64| self.shadow.is_lit(texel_origin + texel_step * t);
        let marcher = Marcher {
            steps,
            ..self.clone()
        };
        marcher.march_lit(ray, &lit, t_start, t_end)
    }

    fn march_lit(
        &self,
        ray: &Ray,
        lit: &impl Fn(f64) -> bool,
        t_start: f64,
        t_end: f64,
    ) -> RaySample {
        match &self.box_medium {
            None => self.march_unbounded(lit, t_start, t_end),
            Some(box_medium) => {
                let Some((a, b)) = medium_segment(Some(box_medium), ray, t_start, t_end) else {
                    return RaySample {
                        visibility: self.average_visibility(lit, t_start, t_end),
                        ..RaySample::EMPTY
                    };
                };
                let (scattering, unshadowed) = self.scatter_in_box(box_medium, ray, lit, a, b);
                RaySample {
                    scattering,
                    alpha: -(-self.extinction * (b - a)).exp_m1(),
                    visibility: weighted_visibility(scattering, unshadowed)
                        .unwrap_or_else(|| self.average_visibility(lit, t_start, t_end)),
                }
            }
        }
    }

    fn march_unbounded(&self, lit: &impl Fn(f64) -> bool, t_start: f64, t_end: f64) -> RaySample {
        let n = self.steps;
        let dt = (t_end - t_start) / n as f64;
        let sigma = self.extinction;
        let decay = (-sigma * dt).exp();
        let per_step = integral_exp(sigma, dt);
        let mut transmittance = 1.0;
        let (mut scattering, mut unshadowed) = (0.0, 0.0);
        for i in 0..n {
            if lit(t_start + (i as f64 + 0.5) * dt) {
                scattering += transmittance;
            }
            unshadowed += transmittance;
            transmittance *= decay;
        }
        RaySample {
            scattering: scattering * per_step,
            alpha: -(-sigma * (t_end - t_start)).exp_m1(),
            visibility: weighted_visibility(scattering, unshadowed)
                .unwrap_or_else(|| self.average_visibility(lit, t_start, t_end)),
        }
    }

    fn average_visibility(&self, lit: &impl Fn(f64) -> bool, t_start: f64, t_end: f64) -> f64 {
        let n = self.steps;
        let dt = (t_end - t_start) / n as f64;
        let lit_steps = (0..n)
            .filter(|&i| lit(t_start + (i as f64 + 0.5) * dt))
            .count();
        lit_steps as f64 / n as f64
    }

    /// ∫ₐᵇ V(t) · e^(−σt·ℓ(t)) · e^(−σt·(t−a)) dt, with ℓ the sunward depth into the box,
    /// taken as linear within each step; and the same integral with V = 1.
    fn scatter_in_box(
        &self,
        box_medium: &BoxMedium,
        ray: &Ray,
        lit: &impl Fn(f64) -> bool,
        a: f64,
        b: f64,
    ) -> (f64, f64) {
        let n = self.steps;
        let dt = (b - a) / n as f64;
        let sigma = self.extinction;
        let cube_origin = box_medium.cube_from_world.transform_point3(ray.origin);
        let cube_step = box_medium.cube_from_world.transform_vector3(ray.direction);
        let depth_at = |t: f64| box_medium.sunward_depth(cube_origin + cube_step * t);
        let mut depth_before = depth_at(a);
        let (mut scattering, mut unshadowed) = (0.0, 0.0);
        for i in 0..n {
            let t0 = a + i as f64 * dt;
            let depth_after = depth_at(t0 + dt);
            let slope = (depth_after - depth_before) / dt;
            let step =
                stretch_integral(sigma, a, [t0, t0 + dt], [depth_before, depth_after], slope);
            if lit(t0 + 0.5 * dt) {
                scattering += step;
            }
            unshadowed += step;
            depth_before = depth_after;
        }
        (scattering, unshadowed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integral_exp_matches_closed_form_and_limits() {
        assert!((integral_exp(2.0, 0.5) - (1.0 - (-1.0f64).exp()) / 2.0).abs() < 1e-15);
        assert!((integral_exp(0.0, 0.5) - 0.5).abs() < 1e-15);
        assert!((integral_exp(-1.0, 1.0) - (1.0f64.exp() - 1.0)).abs() < 1e-12);
        assert!((integral_exp(1e-12, 3.0) - 3.0).abs() < 1e-10);
    }

    /// ∫ e^(−σ·ℓ(t)) · e^(−σ·(t − a)) dt by the midpoint rule, ℓ from the point itself.
    fn box_integral_by_steps(box_medium: &BoxMedium, ray: &Ray, a: f64, b: f64, sigma: f64) -> f64 {
        let steps = 200_000;
        let dt = (b - a) / steps as f64;
        let origin = box_medium.cube_from_world.transform_point3(ray.origin);
        let direction = box_medium.cube_from_world.transform_vector3(ray.direction);
        (0..steps)
            .map(|i| {
                let t = a + (i as f64 + 0.5) * dt;
                let depth = box_medium.sunward_depth(origin + direction * t);
                (-sigma * (depth + t - a)).exp() * dt
            })
            .sum()
    }

    /// A stretch's integral is the same from either end, and finite however steeply the
    /// sunward depth falls in however dense a fog (1000 /m read NaN pixels before).
    #[test]
    fn stretch_integrals_stay_finite_where_the_depth_falls_steeply() {
        let by_steps = |sigma: f64, a: f64, p: f64, q: f64, depth: &dyn Fn(f64) -> f64| {
            let n = 200_000;
            let dt = (q - p) / n as f64;
            (0..n)
                .map(|i| {
                    let t = p + (i as f64 + 0.5) * dt;
                    (-sigma * (depth(t) + t - a)).exp() * dt
                })
                .sum::<f64>()
        };
        for (sigma, beta) in [
            (0.7, -3.0),
            (0.7, -1.0),
            (0.7, 0.0),
            (0.7, 2.0),
            (30.0, -2.0),
        ] {
            let (a, p, q) = (0.5, 1.0, 2.5);
            let depth = |t: f64| 10.0 + beta * (t - p);
            let got = stretch_integral(sigma, a, [p, q], [depth(p), depth(q)], beta);
            let expected = by_steps(sigma, a, p, q, &depth);
            assert!(
                (got - expected).abs() <= 1e-6 * expected,
                "σ {sigma}, β {beta}: {got} against {expected}"
            );
        }
        for (sigma, beta) in [(1000.0, -2.0), (1e30, -2.0), (0.2, -1e25)] {
            let got = stretch_integral(sigma, 0.0, [0.0, 1.0], [2.0, 0.0], beta);
            assert!(got.is_finite() && got >= 0.0, "σ {sigma}, β {beta}: {got}");
        }
    }

    /// A sun with no x component but for rounding (as torus's has, −2·10⁻¹⁷) grazes the
    /// box's x walls: a ray entering through one read the fog up to twice as bright. Closer
    /// still (10⁻²⁰ and below), a line of the sunward depth is so steep that its stretch
    /// read e^(−σ·…) = 0 times an integral of ∞: NaN pixels in min-max and prefiltered.
    #[test]
    fn box_integral_and_sunward_change_hold_where_the_sun_grazes_a_wall() {
        let extent = Extent::Box {
            world_from_cube: glam::Mat4::from_translation(glam::Vec3::new(0.0, 0.0, 4.0))
                * glam::Mat4::from_scale(glam::Vec3::new(3.5, 3.8, 4.0)),
        };
        let sigma = 0.2;
        for x in [-2.1e-17, 0.0, 1e-9, 0.3, 1e-20, -1e-25, 1e-30, 1e-40] {
            let light_travel = DVec3::new(x, -0.342, -0.94).normalize();
            let box_medium = BoxMedium::lit_along(&extent, light_travel, true).expect("a box");
            for (origin, direction) in [
                (DVec3::new(9.0, -1.0, 2.0), DVec3::new(-1.0, 0.1, 0.05)),
                (DVec3::new(-8.0, 2.0, 3.0), DVec3::new(0.9, -0.3, 0.1)),
                (DVec3::new(1.0, -9.0, 5.0), DVec3::new(0.05, 1.0, -0.2)),
            ] {
                let ray = Ray {
                    origin,
                    direction: direction.normalize(),
                    distance_per_depth: 1.0,
                };
                let (a, b) = box_medium.clip(&ray).expect("the ray crosses the box");
                let along = box_medium.along(&ray);
                let expected = box_integral_by_steps(&box_medium, &ray, a, b, sigma);
                let whole = along.integrate(a, b, a, sigma);
                assert!(
                    (whole - expected).abs() <= 1e-6 * expected,
                    "x = {x}, ray from {origin}: {whole} against {expected}"
                );
                // Pieces add up to the whole, the first starting at the entry.
                let pieces: f64 = (0..7)
                    .map(|k| {
                        let at = |k: i32| a + (b - a) * k as f64 / 7.0;
                        along.integrate(at(k), at(k + 1), a, sigma)
                    })
                    .sum();
                assert!(
                    (pieces - expected).abs() <= 1e-6 * expected,
                    "{pieces} against {expected}"
                );
                // The sunward depth's rise and fall, by steps: a grazed wall's jump at
                // the entry, within rounding of it, does not count.
                let depth_at = |t: f64| {
                    let cube = box_medium.cube_from_world.transform_point3(ray.at(t));
                    box_medium.sunward_depth(cube)
                };
                let steps = 100_000;
                let dt = (b - a) / steps as f64;
                let mid = |i: usize| depth_at(a + (i as f64 + 0.5) * dt);
                let stepped: f64 = (1..steps).map(|i| (mid(i) - mid(i - 1)).abs()).sum();
                let change = along.sunward_change(a, b);
                assert!(
                    (change - stepped).abs() <= 1e-3 * stepped.max(1.0),
                    "x = {x}, ray from {origin}: change {change} against {stepped}"
                );
            }
        }
    }
}
