//! Port types: what may flow along an edge, checked before anything runs.

use std::fmt;

/// The type of an operator port or a graph edge.
///
/// A port of type `T` that is fed a `List<T>` maps its operator over the list (see the scheduler);
/// the outputs of such a node become lists too.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum PortType {
    /// A raster image, gray/rgb/rgba × u8/u16/f32 (the pixel format is checked at run time).
    Image,
    /// Image keypoints (position, scale, orientation, response).
    Keypoints,
    /// Feature descriptors, float or binary.
    Descriptors,
    /// Correspondences between two keypoint sets.
    Matches,
    /// A dense row-major f64 matrix.
    Matrix,
    /// Camera intrinsics and distortion.
    Camera,
    /// A rigid transform.
    Pose,
    /// A list of 2-D points.
    Points2D,
    /// 3-D points with optional colors and normals.
    PointCloud,
    /// Feature tracks across images.
    Tracks,
    /// A sparse reconstruction: cameras, posed images, 3-D points.
    Reconstruction,
    /// A triangle mesh.
    Mesh,
    /// A renderable scene.
    Scene,
    /// Animation channels.
    Animation,
    /// A real number.
    Scalar,
    /// A signed integer.
    Integer,
    /// A boolean.
    Bool,
    /// UTF-8 text.
    Text,
    /// Named numbers (name → value).
    Metrics,
    /// A bounding-volume hierarchy over a triangle mesh (for ray casting).
    Bvh,
    /// A list of values of one type.
    List(Box<PortType>),
}

/// Every non-list type, in the order they are documented.
pub const SCALAR_PORT_TYPES: [PortType; 20] = [
    PortType::Image,
    PortType::Keypoints,
    PortType::Descriptors,
    PortType::Matches,
    PortType::Matrix,
    PortType::Camera,
    PortType::Pose,
    PortType::Points2D,
    PortType::PointCloud,
    PortType::Tracks,
    PortType::Reconstruction,
    PortType::Mesh,
    PortType::Scene,
    PortType::Animation,
    PortType::Scalar,
    PortType::Integer,
    PortType::Bool,
    PortType::Text,
    PortType::Metrics,
    PortType::Bvh,
];

impl PortType {
    /// `List<self>`.
    pub fn list_of(self) -> PortType {
        PortType::List(Box::new(self))
    }

    /// The element type if this is a list.
    pub fn element(&self) -> Option<&PortType> {
        match self {
            PortType::List(inner) => Some(inner),
            _ => None,
        }
    }

    /// The name without list wrapping (`Image` for `List<List<Image>>`).
    pub fn base_name(&self) -> &'static str {
        match self {
            PortType::Image => "Image",
            PortType::Keypoints => "Keypoints",
            PortType::Descriptors => "Descriptors",
            PortType::Matches => "Matches",
            PortType::Matrix => "Matrix",
            PortType::Camera => "Camera",
            PortType::Pose => "Pose",
            PortType::Points2D => "Points2D",
            PortType::PointCloud => "PointCloud",
            PortType::Tracks => "Tracks",
            PortType::Reconstruction => "Reconstruction",
            PortType::Mesh => "Mesh",
            PortType::Scene => "Scene",
            PortType::Animation => "Animation",
            PortType::Scalar => "Scalar",
            PortType::Integer => "Integer",
            PortType::Bool => "Bool",
            PortType::Text => "Text",
            PortType::Metrics => "Metrics",
            PortType::Bvh => "Bvh",
            PortType::List(inner) => inner.base_name(),
        }
    }

    /// Parses `Image`, `List<Image>`, `List<List<Scalar>>` (whitespace allowed around `<` and `>`).
    pub fn parse(text: &str) -> Option<PortType> {
        let text = text.trim();
        if let Some(rest) = text.strip_prefix("List") {
            let inner = rest.trim_start().strip_prefix('<')?.strip_suffix('>')?;
            return PortType::parse(inner).map(PortType::list_of);
        }
        SCALAR_PORT_TYPES
            .iter()
            .find(|t| t.base_name() == text)
            .cloned()
    }
}

impl fmt::Display for PortType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PortType::List(inner) => write!(f, "List<{inner}>"),
            other => f.write_str(other.base_name()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn display_parse_round_trip() {
        for t in SCALAR_PORT_TYPES {
            let nested = t.clone().list_of().list_of();
            assert_eq!(PortType::parse(&t.to_string()), Some(t.clone()));
            assert_eq!(PortType::parse(&nested.to_string()), Some(nested));
        }
        assert_eq!(
            PortType::parse(" List < Image > "),
            Some(PortType::Image.list_of())
        );
        assert_eq!(PortType::parse("Imag"), None);
        assert_eq!(PortType::parse("List<Image"), None);
    }
}
