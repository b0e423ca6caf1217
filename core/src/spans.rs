//! Lit intervals along a ray, joined where they touch before they are integrated.

/// Takes intervals in increasing order and reports each run of touching or overlapping
/// ones once, as one interval: each report is integrated in closed form, with an
/// exponential or two, and a mostly lit ray crosses hundreds of texels or samples.
#[derive(Default)]
pub(crate) struct JoinedSpans {
    /// The run not yet reported.
    pending: Option<(f64, f64)>,
}

impl JoinedSpans {
    /// Adds [`s0`, `s1`] (nothing if it is empty), reporting the run before it to `visit`
    /// if the two do not touch.
    #[inline]
    pub(crate) fn push(&mut self, s0: f64, s1: f64, visit: &mut impl FnMut(f64, f64)) {
        if s1 > s0 {
            self.pending = match self.pending {
                // A comparison: s1 is no NaN here, and f64::max's NaN handling costs a walk's
                // every texel.
                Some((p0, p1)) if s0 <= p1 => Some((p0, if s1 > p1 { s1 } else { p1 })),
                Some((p0, p1)) => {
                    visit(p0, p1);
                    Some((s0, s1))
                }
                None => Some((s0, s1)),
            };
        }
    }

    /// Reports the last run.
    #[inline]
    pub(crate) fn finish(self, visit: &mut impl FnMut(f64, f64)) {
        if let Some((p0, p1)) = self.pending {
            visit(p0, p1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn touching_and_overlapping_intervals_are_reported_as_one() {
        let mut reported = Vec::new();
        let mut visit = |a, b| reported.push((a, b));
        let mut spans = JoinedSpans::default();
        for (a, b) in [
            (0.0, 1.0),
            (1.0, 2.0),
            (1.5, 1.8),
            (3.0, 3.0),
            (3.0, 4.0),
            (5.0, 4.5),
        ] {
            spans.push(a, b, &mut visit);
        }
        spans.push(6.0, 7.0, &mut visit);
        spans.finish(&mut visit);
        assert_eq!(reported, [(0.0, 2.0), (3.0, 4.0), (6.0, 7.0)]);
    }
}
