//! A hand-written decoder for the WOMD `Scenario` wire format, into the [`womd_proto`] structs.
//!
//! prost's generic decoding spends most of a WOMD record's time dispatching the ten one-byte
//! fields of each of its ~10,000 `ObjectState`s and the three of each `MapPoint`. Here every
//! message is a `match` on its one-byte keys over a byte slice, with no per-field indirection.
//! The rules are prost's, so the two agree on every input (a test holds them to it on encoded
//! scenes and on thousands of damaged ones): the last value of a scalar wins, a repeated scalar
//! is read packed or unpacked, a repeated message field appends, an optional message field and
//! a repeated oneof member merge, unknown fields (groups included) are skipped, nesting stops at
//! prost's recursion limit, strings must be UTF-8. An error names the field path, e.g.
//! `Scenario.tracks[3]: Track.states[40]: ObjectState: buffer underflow`.
//!
//! [`womd_proto`]: super::womd_proto

use std::fmt;

use super::womd_proto as pb;

/// prost's nesting limit (messages and groups), counted the same way.
const RECURSION_LIMIT: u32 = 100;

/// Why bytes are not a `Scenario`: the wire-format fault and the fields that lead to it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WireError {
    path: Vec<String>,
    fault: String,
}

impl WireError {
    fn new(fault: impl Into<String>) -> Self {
        Self {
            path: Vec::new(),
            fault: fault.into(),
        }
    }

    /// Prefixes the field (`Message.field`, with its index when repeated) the fault lies
    /// under; called on the error path only.
    fn within(mut self, field: impl Into<String>) -> Self {
        self.path.push(field.into());
        self
    }
}

impl fmt::Display for WireError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for p in self.path.iter().rev() {
            write!(f, "{p}: ")?;
        }
        f.write_str(&self.fault)
    }
}

impl std::error::Error for WireError {}

type Result<T> = std::result::Result<T, WireError>;

const VARINT: u8 = 0;
const FIXED64: u8 = 1;
const LEN: u8 = 2;
const START_GROUP: u8 = 3;
const END_GROUP: u8 = 4;
const FIXED32: u8 = 5;

/// A cursor over one message's bytes.
struct Reader<'a> {
    b: &'a [u8],
    i: usize,
}

impl<'a> Reader<'a> {
    fn new(b: &'a [u8]) -> Self {
        Self { b, i: 0 }
    }

    #[inline(always)]
    fn more(&self) -> bool {
        self.i < self.b.len()
    }

    #[inline(always)]
    fn varint(&mut self) -> Result<u64> {
        // One byte is by far the most common case (keys, small ints, short lengths).
        if let Some(&b) = self.b.get(self.i) {
            if b < 0x80 {
                self.i += 1;
                return Ok(b as u64);
            }
        }
        self.varint_slow()
    }

    fn varint_slow(&mut self) -> Result<u64> {
        let mut v = 0u64;
        for k in 0..10 {
            let Some(&b) = self.b.get(self.i + k) else {
                break;
            };
            v |= ((b & 0x7f) as u64) << (7 * k);
            if b < 0x80 {
                // The tenth byte carries one bit of a u64; more is an overflow.
                if k == 9 && b >= 2 {
                    break;
                }
                self.i += k + 1;
                return Ok(v);
            }
        }
        Err(WireError::new("invalid varint"))
    }

    /// A field's key: (tag, wire type).
    #[inline(always)]
    fn key(&mut self) -> Result<(u32, u8)> {
        let k = self.varint()?;
        if k > u32::MAX as u64 {
            return Err(WireError::new(format!("invalid key value: {k}")));
        }
        let wire = (k & 7) as u8;
        if wire > FIXED32 {
            return Err(WireError::new(format!("invalid wire type value: {wire}")));
        }
        let tag = (k >> 3) as u32;
        if tag == 0 {
            return Err(WireError::new("invalid tag value: 0"));
        }
        Ok((tag, wire))
    }

    #[inline(always)]
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if self.b.len() - self.i < n {
            return Err(WireError::new("buffer underflow"));
        }
        let s = &self.b[self.i..self.i + n];
        self.i += n;
        Ok(s)
    }

    #[inline(always)]
    fn f64(&mut self) -> Result<f64> {
        let s = self.take(8)?;
        Ok(f64::from_le_bytes(s.try_into().expect("8 bytes")))
    }

    #[inline(always)]
    fn f32(&mut self) -> Result<f32> {
        let s = self.take(4)?;
        Ok(f32::from_le_bytes(s.try_into().expect("4 bytes")))
    }

    /// A length-delimited field's bytes.
    #[inline(always)]
    fn bytes(&mut self) -> Result<&'a [u8]> {
        let n = self.varint()?;
        if n > (self.b.len() - self.i) as u64 {
            return Err(WireError::new("buffer underflow"));
        }
        self.take(n as usize)
    }

    /// Skips an unknown field; `depth` is what is left of the recursion limit.
    fn skip(&mut self, wire: u8, tag: u32, depth: u32) -> Result<()> {
        if depth == 0 {
            return Err(WireError::new("recursion limit reached"));
        }
        match wire {
            VARINT => {
                self.varint()?;
            }
            FIXED64 => {
                self.take(8)?;
            }
            FIXED32 => {
                self.take(4)?;
            }
            LEN => {
                self.bytes()?;
            }
            START_GROUP => loop {
                let (t, w) = self.key()?;
                if w == END_GROUP {
                    if t != tag {
                        return Err(WireError::new("unexpected end group tag"));
                    }
                    break;
                }
                self.skip(w, t, depth - 1)?;
            },
            _ => return Err(WireError::new("unexpected end group tag")),
        }
        Ok(())
    }
}

fn wire_type_error(got: u8, want: u8) -> WireError {
    WireError::new(format!("invalid wire type: {got} (expected {want})"))
}

#[inline(always)]
fn expect(got: u8, want: u8) -> Result<()> {
    if got == want {
        Ok(())
    } else {
        Err(wire_type_error(got, want))
    }
}

/// A message's fields, decoded by `field` (which returns `Ok(false)` for a tag it does not
/// know, to be skipped). `depth` is the recursion budget of this message's fields.
#[inline(always)]
fn fields<'a>(
    b: &'a [u8],
    depth: u32,
    mut field: impl FnMut(&mut Reader<'a>, u32, u8) -> Result<bool>,
) -> Result<()> {
    let mut r = Reader::new(b);
    while r.more() {
        let (tag, wire) = r.key()?;
        if !field(&mut r, tag, wire)? {
            r.skip(wire, tag, depth)?;
        }
    }
    Ok(())
}

/// A nested message's bytes, checked the way prost checks before entering it.
#[inline(always)]
fn nested<'a>(r: &mut Reader<'a>, wire: u8, depth: u32) -> Result<&'a [u8]> {
    expect(wire, LEN)?;
    if depth == 0 {
        return Err(WireError::new("recursion limit reached"));
    }
    r.bytes()
}

#[inline(always)]
fn double(r: &mut Reader, wire: u8) -> Result<f64> {
    expect(wire, FIXED64)?;
    r.f64()
}

#[inline(always)]
fn float(r: &mut Reader, wire: u8) -> Result<f32> {
    expect(wire, FIXED32)?;
    r.f32()
}

#[inline(always)]
fn int(r: &mut Reader, wire: u8) -> Result<u64> {
    expect(wire, VARINT)?;
    r.varint()
}

/// A repeated varint field, packed or not.
fn ints(r: &mut Reader, wire: u8, out: &mut Vec<i64>) -> Result<()> {
    if wire == LEN {
        let mut p = Reader::new(r.bytes()?);
        while p.more() {
            out.push(p.varint()? as i64);
        }
        Ok(())
    } else {
        out.push(int(r, wire)? as i64);
        Ok(())
    }
}

/// Decodes one `Scenario` record.
pub fn decode_scenario(b: &[u8]) -> Result<pb::Scenario> {
    let mut sc = pb::Scenario::default();
    let d = RECURSION_LIMIT;
    fields(b, d, |r, tag, wire| {
        match tag {
            5 => {
                let at = |e: WireError| e.within("Scenario.scenario_id");
                expect(wire, LEN).map_err(at)?;
                let s = std::str::from_utf8(r.bytes().map_err(at)?).map_err(|_| {
                    at(WireError::new(
                        "invalid string value: data is not UTF-8 encoded",
                    ))
                })?;
                sc.scenario_id = Some(s.to_string());
            }
            1 => {
                let at = |e: WireError| e.within("Scenario.timestamps_seconds");
                if wire == LEN {
                    let mut p = Reader::new(r.bytes().map_err(at)?);
                    while p.more() {
                        sc.timestamps_seconds.push(p.f64().map_err(at)?);
                    }
                } else {
                    sc.timestamps_seconds.push(double(r, wire).map_err(at)?);
                }
            }
            10 => {
                let v = int(r, wire).map_err(|e| e.within("Scenario.current_time_index"))?;
                sc.current_time_index = Some(v as i32);
            }
            2 => {
                let k = sc.tracks.len();
                let at = |e: WireError| e.within(format!("Scenario.tracks[{k}]"));
                let m = nested(r, wire, d).map_err(at)?;
                sc.tracks.push(track(m, d - 1).map_err(at)?);
            }
            7 => {
                let m = nested(r, wire, d).map_err(|e| e.within("Scenario.dynamic_map_states"))?;
                let mut s = pb::DynamicMapState::default();
                fields(m, d - 1, |r, tag, wire| {
                    if tag != 1 {
                        return Ok(false);
                    }
                    let m = nested(r, wire, d - 1)?;
                    s.lane_states.push(signal_state(m, d - 2)?);
                    Ok(true)
                })
                .map_err(|e| e.within("Scenario.dynamic_map_states"))?;
                sc.dynamic_map_states.push(s);
            }
            8 => {
                let k = sc.map_features.len();
                let at = |e: WireError| e.within(format!("Scenario.map_features[{k}]"));
                let m = nested(r, wire, d).map_err(at)?;
                sc.map_features.push(map_feature(m, d - 1).map_err(at)?);
            }
            6 => {
                let v = int(r, wire).map_err(|e| e.within("Scenario.sdc_track_index"))?;
                sc.sdc_track_index = Some(v as i32);
            }
            4 => {
                let mut v = Vec::new();
                ints(r, wire, &mut v).map_err(|e| e.within("Scenario.objects_of_interest"))?;
                sc.objects_of_interest
                    .extend(v.into_iter().map(|x| x as i32));
            }
            11 => {
                let m = nested(r, wire, d).map_err(|e| e.within("Scenario.tracks_to_predict"))?;
                let mut p = pb::RequiredPrediction::default();
                fields(m, d - 1, |r, tag, wire| {
                    match tag {
                        1 => p.track_index = Some(int(r, wire)? as i32),
                        2 => p.difficulty = Some(int(r, wire)? as i32),
                        _ => return Ok(false),
                    }
                    Ok(true)
                })
                .map_err(|e| e.within("Scenario.tracks_to_predict"))?;
                sc.tracks_to_predict.push(p);
            }
            _ => return Ok(false),
        }
        Ok(true)
    })?;
    Ok(sc)
}

fn track(b: &[u8], d: u32) -> Result<pb::Track> {
    let mut t = pb::Track::default();
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => t.id = Some(int(r, wire).map_err(|e| e.within("Track.id"))? as i32),
            2 => {
                t.object_type =
                    Some(int(r, wire).map_err(|e| e.within("Track.object_type"))? as i32)
            }
            3 => {
                let k = t.states.len();
                let at = |e: WireError| e.within(format!("Track.states[{k}]"));
                let m = nested(r, wire, d).map_err(at)?;
                t.states.push(object_state(m, d - 1).map_err(at)?);
            }
            _ => return Ok(false),
        }
        Ok(true)
    })?;
    Ok(t)
}

/// The hot loop of a WOMD record: ~10,000 of these, ten fixed-width fields each.
fn object_state(b: &[u8], d: u32) -> Result<pb::ObjectState> {
    let mut s = pb::ObjectState::default();
    fields(b, d, |r, tag, wire| {
        match tag {
            2 => s.center_x = Some(double(r, wire)?),
            3 => s.center_y = Some(double(r, wire)?),
            4 => s.center_z = Some(double(r, wire)?),
            5 => s.length = Some(float(r, wire)?),
            6 => s.width = Some(float(r, wire)?),
            7 => s.height = Some(float(r, wire)?),
            8 => s.heading = Some(float(r, wire)?),
            9 => s.velocity_x = Some(float(r, wire)?),
            10 => s.velocity_y = Some(float(r, wire)?),
            11 => s.valid = Some(int(r, wire)? != 0),
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("ObjectState"))?;
    Ok(s)
}

fn map_point_into(p: &mut pb::MapPoint, b: &[u8], d: u32) -> Result<()> {
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => p.x = Some(double(r, wire)?),
            2 => p.y = Some(double(r, wire)?),
            3 => p.z = Some(double(r, wire)?),
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("MapPoint"))
}

/// Appends a `MapPoint` (a repeated field) read from `r`.
#[inline(always)]
fn push_point(r: &mut Reader, wire: u8, d: u32, out: &mut Vec<pb::MapPoint>) -> Result<()> {
    let m = nested(r, wire, d)?;
    let mut p = pb::MapPoint::default();
    map_point_into(&mut p, m, d - 1)?;
    out.push(p);
    Ok(())
}

/// Merges a `MapPoint` into an optional field (a repeated occurrence merges, as in prost).
fn merge_point(r: &mut Reader, wire: u8, d: u32, into: &mut Option<pb::MapPoint>) -> Result<()> {
    let m = nested(r, wire, d)?;
    map_point_into(into.get_or_insert_with(Default::default), m, d - 1)
}

fn signal_state(b: &[u8], d: u32) -> Result<pb::TrafficSignalLaneState> {
    let mut s = pb::TrafficSignalLaneState::default();
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => s.lane = Some(int(r, wire)? as i64),
            2 => s.state = Some(int(r, wire)? as i32),
            3 => merge_point(r, wire, d, &mut s.stop_point)?,
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("TrafficSignalLaneState"))?;
    Ok(s)
}

fn map_feature(b: &[u8], d: u32) -> Result<pb::MapFeature> {
    use pb::FeatureData as F;
    let mut f = pb::MapFeature::default();
    fields(b, d, |r, tag, wire| {
        if tag == 1 {
            f.id = Some(int(r, wire).map_err(|e| e.within("MapFeature.id"))? as i64);
            return Ok(true);
        }
        // A oneof member merges into the same member, and replaces a different one.
        macro_rules! member {
            ($variant:ident, $decode:ident, $name:literal) => {{
                let m = nested(r, wire, d).map_err(|e| e.within($name))?;
                let mut v = match f.feature_data.take() {
                    Some(F::$variant(v)) => v,
                    _ => Default::default(),
                };
                $decode(&mut v, m, d - 1).map_err(|e| e.within($name))?;
                f.feature_data = Some(F::$variant(v));
            }};
        }
        match tag {
            3 => member!(Lane, lane_center, "MapFeature.lane"),
            4 => member!(RoadLine, road_line, "MapFeature.road_line"),
            5 => member!(RoadEdge, road_edge, "MapFeature.road_edge"),
            7 => member!(StopSign, stop_sign, "MapFeature.stop_sign"),
            8 => member!(Crosswalk, crosswalk, "MapFeature.crosswalk"),
            9 => member!(SpeedBump, speed_bump, "MapFeature.speed_bump"),
            10 => member!(Driveway, driveway, "MapFeature.driveway"),
            _ => return Ok(false),
        }
        Ok(true)
    })?;
    Ok(f)
}

fn boundary(b: &[u8], d: u32) -> Result<pb::BoundarySegment> {
    let mut s = pb::BoundarySegment::default();
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => s.lane_start_index = Some(int(r, wire)? as i32),
            2 => s.lane_end_index = Some(int(r, wire)? as i32),
            3 => s.boundary_feature_id = Some(int(r, wire)? as i64),
            4 => s.boundary_type = Some(int(r, wire)? as i32),
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("BoundarySegment"))?;
    Ok(s)
}

fn neighbor(b: &[u8], d: u32) -> Result<pb::LaneNeighbor> {
    let mut n = pb::LaneNeighbor::default();
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => n.feature_id = Some(int(r, wire)? as i64),
            2 => n.self_start_index = Some(int(r, wire)? as i32),
            3 => n.self_end_index = Some(int(r, wire)? as i32),
            4 => n.neighbor_start_index = Some(int(r, wire)? as i32),
            5 => n.neighbor_end_index = Some(int(r, wire)? as i32),
            6 => {
                let m = nested(r, wire, d)?;
                n.boundaries.push(boundary(m, d - 1)?);
            }
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("LaneNeighbor"))?;
    Ok(n)
}

fn lane_center(l: &mut pb::LaneCenter, b: &[u8], d: u32) -> Result<()> {
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => l.speed_limit_mph = Some(double(r, wire)?),
            2 => l.r#type = Some(int(r, wire)? as i32),
            3 => l.interpolating = Some(int(r, wire)? != 0),
            8 => push_point(r, wire, d, &mut l.polyline)?,
            9 => ints(r, wire, &mut l.entry_lanes)?,
            10 => ints(r, wire, &mut l.exit_lanes)?,
            13 | 14 => {
                let m = nested(r, wire, d)?;
                let s = boundary(m, d - 1)?;
                if tag == 13 {
                    &mut l.left_boundaries
                } else {
                    &mut l.right_boundaries
                }
                .push(s);
            }
            11 | 12 => {
                let m = nested(r, wire, d)?;
                let n = neighbor(m, d - 1)?;
                if tag == 11 {
                    &mut l.left_neighbors
                } else {
                    &mut l.right_neighbors
                }
                .push(n);
            }
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("LaneCenter"))
}

/// Road lines and road edges: a type (field 1) and a polyline (field 2).
fn typed_polyline(
    ty: &mut Option<i32>,
    pts: &mut Vec<pb::MapPoint>,
    b: &[u8],
    d: u32,
    name: &'static str,
) -> Result<()> {
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => *ty = Some(int(r, wire)? as i32),
            2 => push_point(r, wire, d, pts)?,
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within(name))
}

fn road_line(l: &mut pb::RoadLine, b: &[u8], d: u32) -> Result<()> {
    typed_polyline(&mut l.r#type, &mut l.polyline, b, d, "RoadLine")
}

fn road_edge(l: &mut pb::RoadEdge, b: &[u8], d: u32) -> Result<()> {
    typed_polyline(&mut l.r#type, &mut l.polyline, b, d, "RoadEdge")
}

fn stop_sign(s: &mut pb::StopSign, b: &[u8], d: u32) -> Result<()> {
    fields(b, d, |r, tag, wire| {
        match tag {
            1 => ints(r, wire, &mut s.lane)?,
            2 => merge_point(r, wire, d, &mut s.position)?,
            _ => return Ok(false),
        }
        Ok(true)
    })
    .map_err(|e| e.within("StopSign"))
}

/// Crosswalks, speed bumps and driveways: one repeated `MapPoint` polygon, field 1.
fn polygon(out: &mut Vec<pb::MapPoint>, b: &[u8], d: u32) -> Result<()> {
    fields(b, d, |r, tag, wire| {
        if tag != 1 {
            return Ok(false);
        }
        push_point(r, wire, d, out)?;
        Ok(true)
    })
}

fn crosswalk(c: &mut pb::Crosswalk, b: &[u8], d: u32) -> Result<()> {
    polygon(&mut c.polygon, b, d).map_err(|e| e.within("Crosswalk"))
}

fn speed_bump(c: &mut pb::SpeedBump, b: &[u8], d: u32) -> Result<()> {
    polygon(&mut c.polygon, b, d).map_err(|e| e.within("SpeedBump"))
}

fn driveway(c: &mut pb::Driveway, b: &[u8], d: u32) -> Result<()> {
    polygon(&mut c.polygon, b, d).map_err(|e| e.within("Driveway"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    /// The fixture of the WOMD reader's tests, with the fields it leaves empty filled.
    fn rich() -> pb::Scenario {
        let mut sc = crate::io::womd::tests::scenario();
        if let Some(pb::FeatureData::Lane(l)) = &mut sc.map_features[0].feature_data {
            l.entry_lanes = vec![5, -1, 1 << 40];
            l.right_neighbors = vec![pb::LaneNeighbor {
                feature_id: Some(2),
                self_start_index: Some(0),
                self_end_index: Some(1),
                neighbor_start_index: Some(-3),
                neighbor_end_index: Some(1),
                boundaries: vec![pb::BoundarySegment {
                    lane_start_index: Some(0),
                    lane_end_index: Some(1),
                    boundary_feature_id: Some(30),
                    boundary_type: Some(2),
                }],
            }];
        }
        sc
    }

    /// prost and this decoder on the same bytes: both succeed with equal messages, or both fail.
    fn agree(bytes: &[u8]) -> bool {
        match (pb::Scenario::decode(bytes), decode_scenario(bytes)) {
            (Ok(a), Ok(b)) => {
                // Bytes, not PartialEq: a damaged float may be NaN, and its bits must agree too.
                assert!(
                    a.encode_to_vec() == b.encode_to_vec(),
                    "decoded differently:\nprost {a:?}\nwire  {b:?}"
                );
                true
            }
            (Err(_), Err(_)) => false,
            (a, b) => panic!("prost {a:?}\nwire {b:?}\non {bytes:?}"),
        }
    }

    fn key(tag: u32, wire: u8, out: &mut Vec<u8>) {
        prost::encoding::encode_varint(((tag as u64) << 3) | wire as u64, out);
    }

    #[test]
    fn encoded_scenes_decode_as_prost_decodes_them() {
        assert!(agree(&rich().encode_to_vec()));
        assert!(agree(&[]));
        let samples = crate::io::discover(&std::path::PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/data/samples"
        )))
        .unwrap();
        assert!(samples.len() >= 4);
        for p in samples {
            for scene in crate::io::load_scenes(&p, &Default::default()).unwrap() {
                let bytes = crate::io::womd::scene_to_scenario(&scene).encode_to_vec();
                assert!(agree(&bytes), "{}", p.display());
            }
        }
    }

    #[test]
    fn the_wire_formats_prost_accepts_are_accepted_the_same_way() {
        let mut b = rich().encode_to_vec();
        // Packed timestamps, unpacked exit lanes (the fixture's are packed), a repeated
        // scalar (last wins), a repeated optional message (merges), a oneof member that
        // switches (replaces) then repeats (merges), and unknown fields of every wire type,
        // groups nested in groups included.
        key(1, LEN, &mut b);
        b.extend([16, 0, 0, 0, 0, 0, 0, 0xf0, 0x3f]);
        b.extend([0, 0, 0, 0, 0, 0, 0, 0x40]);
        key(10, VARINT, &mut b);
        b.push(3);
        let mut f = Vec::new();
        key(1, VARINT, &mut f);
        f.push(77);
        let mut edge = Vec::new();
        key(1, VARINT, &mut edge);
        edge.push(2);
        key(5, LEN, &mut f);
        f.push(edge.len() as u8);
        f.extend(&edge);
        let mut lane = Vec::new();
        key(10, VARINT, &mut lane);
        lane.push(9);
        key(10, VARINT, &mut lane);
        lane.push(8);
        key(3, LEN, &mut f);
        f.push(lane.len() as u8);
        f.extend(&lane);
        let mut lane2 = Vec::new();
        key(1, FIXED64, &mut lane2);
        lane2.extend(25.0f64.to_le_bytes());
        key(99, FIXED32, &mut lane2);
        lane2.extend([1, 2, 3, 4]);
        key(98, START_GROUP, &mut lane2);
        key(97, START_GROUP, &mut lane2);
        key(96, VARINT, &mut lane2);
        lane2.push(1);
        key(97, END_GROUP, &mut lane2);
        key(98, END_GROUP, &mut lane2);
        key(3, LEN, &mut f);
        f.push(lane2.len() as u8);
        f.extend(&lane2);
        let mut stop = Vec::new();
        for (tag, x) in [(1u32, 1.0f64), (2, 2.0)] {
            let mut p = Vec::new();
            key(tag, FIXED64, &mut p);
            p.extend(x.to_le_bytes());
            key(2, LEN, &mut stop);
            stop.push(p.len() as u8);
            stop.extend(p);
        }
        key(7, LEN, &mut f);
        f.push(stop.len() as u8);
        f.extend(&stop);
        key(8, LEN, &mut b);
        b.push(f.len() as u8);
        b.extend(&f);
        key(200, FIXED64, &mut b);
        b.extend([0; 8]);
        key(201, LEN, &mut b);
        b.extend([2, 0xff, 0xff]);
        assert!(agree(&b));
        let sc = decode_scenario(&b).unwrap();
        assert_eq!(sc.current_time_index, Some(3));
        assert_eq!(sc.timestamps_seconds[5..], [1.0, 2.0]);
        let last = sc.map_features.last().unwrap();
        let Some(pb::FeatureData::StopSign(s)) = &last.feature_data else {
            panic!("{last:?}")
        };
        assert_eq!(
            s.position.as_ref().map(|p| (p.x, p.y)),
            Some((Some(1.0), Some(2.0)))
        );
    }

    /// A deterministic xorshift, for damage that is the same on every run.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn below(&mut self, n: usize) -> usize {
            (self.next() % n as u64) as usize
        }
    }

    #[test]
    fn damaged_records_are_refused_exactly_where_prost_refuses_them() {
        let good = rich().encode_to_vec();
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let (mut ok, mut bad) = (0, 0);
        for _ in 0..20_000 {
            let mut b = good.clone();
            for _ in 0..1 + rng.below(3) {
                let at = rng.below(b.len());
                match rng.below(5) {
                    0 => b[at] ^= 1 << rng.below(8),
                    1 => b[at] = rng.next() as u8,
                    2 => b.truncate(at),
                    3 => {
                        b.remove(at);
                    }
                    _ => b.insert(at, rng.next() as u8),
                }
                if b.is_empty() {
                    break;
                }
            }
            if agree(&b) {
                ok += 1
            } else {
                bad += 1
            }
        }
        // Both outcomes are exercised in numbers, not just one of them.
        assert!(ok > 1000 && bad > 1000, "{ok} decoded, {bad} refused");
    }

    #[test]
    fn nesting_stops_at_prosts_recursion_limit() {
        for depth in [50usize, 99, 100, 101, 150] {
            let mut b = Vec::new();
            for _ in 0..depth {
                key(300, START_GROUP, &mut b);
            }
            for _ in 0..depth {
                key(300, END_GROUP, &mut b);
            }
            assert_eq!(agree(&b), depth <= 100, "groups nested {depth} deep");
        }
        let mut b = Vec::new();
        key(300, START_GROUP, &mut b);
        key(301, END_GROUP, &mut b);
        assert!(!agree(&b));
        let mut b = Vec::new();
        key(300, END_GROUP, &mut b);
        assert!(!agree(&b));
    }

    #[test]
    fn errors_name_the_field_path_and_the_fault() {
        let mut sc = rich();
        sc.tracks[1].states[3].center_y = None;
        let mut b = sc.encode_to_vec();
        // Re-type center_x (fixed64) of track 1, state 3 as a varint: find its key byte
        // after the fifth occurrence of the state's encoded prefix.
        let state = sc.tracks[1].states[3].encode_to_vec();
        let pos = b
            .windows(state.len())
            .enumerate()
            .filter(|(_, w)| *w == state.as_slice())
            .map(|(i, _)| i)
            .nth(0)
            .unwrap();
        assert_eq!(b[pos], (2 << 3) | FIXED64);
        b[pos] = 2 << 3;
        let e = decode_scenario(&b).unwrap_err().to_string();
        assert!(pb::Scenario::decode(b.as_slice()).is_err());
        assert_eq!(
            e,
            "Scenario.tracks[1]: Track.states[3]: ObjectState: invalid wire type: 0 (expected 1)"
        );
        let e = decode_scenario(&[0x12, 0x05, 0x08])
            .unwrap_err()
            .to_string();
        assert_eq!(e, "Scenario.tracks[0]: buffer underflow");
        let e = decode_scenario(&[0x2a, 0x02, 0xc3, 0x28])
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "Scenario.scenario_id: invalid string value: data is not UTF-8 encoded"
        );
    }
}
