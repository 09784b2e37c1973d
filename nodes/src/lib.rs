//! # ocellus-nodes
//!
//! The built-in operators, one module per family. An operator's id is `family.name`. Algorithms
//! are plain functions with their own tests; each operator wrapper around one is thin.

pub mod analyze;
pub mod animate;
pub mod capture;
pub mod describe;
pub mod detect;
pub mod filter;
#[doc(hidden)]
pub mod fuzz;
pub mod geometry;
pub mod io;
pub mod learn;
/// The `match` family (descriptor and patch matching); `match` is a keyword, hence the name.
pub mod matching;
pub mod mesh;
pub mod optimize;
pub mod render;
pub mod segment;
pub mod sensor;
pub mod sfm;
pub mod texture;
pub mod video;

use ocellus_engine::op::{Registry, RegistryError};

/// Registers every built-in operator.
pub fn register_builtins(registry: &mut Registry) -> Result<(), RegistryError> {
    registry.register::<capture::pattern::Pattern>()?;
    registry.register::<animate::cloth::Cloth>()?;
    registry.register::<animate::pick::Pick>()?;
    registry.register::<animate::chain::Skin>()?;
    registry.register::<animate::chain::Ik>()?;
    registry.register::<animate::blend::BlendShapes>()?;
    registry.register::<video::kalman::KalmanTrack>()?;
    registry.register::<video::particle::ParticleTrack>()?;
    registry.register::<capture::sequence::Sequence>()?;
    registry.register::<capture::moving::MovingShapes>()?;
    registry.register::<capture::moving::Select>()?;
    registry.register::<capture::moving_camera::MovingCamera>()?;
    registry.register::<capture::render::CaptureRender>()?;
    registry.register::<sfm::pairs::MatchPairs>()?;
    registry.register::<sfm::pair_lists::PairLists>()?;
    registry.register::<sfm::tracks::TracksOp>()?;
    registry.register::<sfm::incremental::Incremental>()?;
    registry.register::<filter::grayscale::Grayscale>()?;
    registry.register::<filter::color::ConvertColor>()?;
    registry.register::<filter::convert::ConvertType>()?;
    registry.register::<filter::convert::SplitChannels>()?;
    registry.register::<filter::convert::MergeChannels>()?;
    registry.register::<filter::composite::Over>()?;
    registry.register::<filter::composite::Radiometric>()?;
    registry.register::<filter::gaussian::Gaussian>()?;
    registry.register::<filter::box_filter::BoxFilter>()?;
    registry.register::<filter::sobel::Sobel>()?;
    registry.register::<filter::sobel::Scharr>()?;
    registry.register::<filter::convolve::Convolve>()?;
    registry.register::<filter::derivatives::Prewitt>()?;
    registry.register::<filter::derivatives::Laplacian>()?;
    registry.register::<filter::derivatives::Log>()?;
    registry.register::<filter::derivatives::Dog>()?;
    registry.register::<filter::derivatives::Unsharp>()?;
    registry.register::<filter::morphology::Erode>()?;
    registry.register::<filter::morphology::Dilate>()?;
    registry.register::<filter::morphology::Morphology>()?;
    registry.register::<filter::median::Median>()?;
    registry.register::<filter::bilateral::Bilateral>()?;
    registry.register::<filter::kuwahara::Kuwahara>()?;
    registry.register::<filter::rank::MinFilter>()?;
    registry.register::<filter::rank::MaxFilter>()?;
    registry.register::<filter::frequency::fft::FftOp>()?;
    registry.register::<filter::frequency::fft::IfftOp>()?;
    registry.register::<filter::frequency::pass::FrequencyFilter>()?;
    registry.register::<filter::frequency::dct::Dct>()?;
    registry.register::<filter::frequency::haar::Haar>()?;
    registry.register::<filter::noise::Noise>()?;
    registry.register::<filter::hit_or_miss::HitOrMiss>()?;
    registry.register::<filter::hit_or_miss::Thinning>()?;
    registry.register::<filter::hit_or_miss::Thickening>()?;
    registry.register::<filter::hit_or_miss::Skeleton>()?;
    registry.register::<filter::distance::DistanceTransform>()?;
    registry.register::<filter::flow::Lic>()?;
    registry.register::<filter::flow::EdgeTangentFlow>()?;
    registry.register::<filter::resize::Resize>()?;
    registry.register::<filter::pyramid::PyrDown>()?;
    registry.register::<filter::pyramid::PyrUp>()?;
    registry.register::<filter::pyramid::Pyramid>()?;
    registry.register::<filter::pyramid::PyramidReconstruct>()?;
    registry.register::<filter::integral::Integral>()?;
    registry.register::<filter::warp::WarpAffine>()?;
    registry.register::<filter::warp::WarpPerspective>()?;
    registry.register::<describe::sift::Sift>()?;
    registry.register::<describe::features::Features>()?;
    registry.register::<detect::canny::Canny>()?;
    registry.register::<detect::mser::Mser>()?;
    registry.register::<detect::qr::QrFinder>()?;
    registry.register::<detect::chessboard::Chessboard>()?;
    registry.register::<detect::marker::Aruco>()?;
    registry.register::<detect::corners::Corners>()?;
    registry.register::<detect::fast::Fast>()?;
    registry.register::<detect::hough::HoughLines>()?;
    registry.register::<detect::hough::HoughSegments>()?;
    registry.register::<detect::hough_circles::HoughCircles>()?;
    registry.register::<detect::template::TemplateMatch>()?;
    registry.register::<describe::orb::Orb>()?;
    registry.register::<describe::brief::Brief>()?;
    registry.register::<describe::hog::Hog>()?;
    registry.register::<video::klt::TrackKlt>()?;
    registry.register::<video::klt_tracker::KltTrackerOp>()?;
    registry.register::<video::block_match::BlockMatch>()?;
    registry.register::<video::horn_schunck::FlowHornSchunck>()?;
    registry.register::<video::dense_lk::FlowLk>()?;
    registry.register::<analyze::stats::Stats>()?;
    registry.register::<analyze::running_stats::RunningStatsOp>()?;
    registry.register::<analyze::track_error::TrackError>()?;
    registry.register::<analyze::quality::Quality>()?;
    registry.register::<analyze::depth_agreement::DepthAgreement>()?;
    registry.register::<analyze::evaluate::Evaluate>()?;
    registry.register::<analyze::evaluate::Roc>()?;
    registry.register::<filter::threshold::Threshold>()?;
    registry.register::<filter::threshold::AdaptiveThreshold>()?;
    registry.register::<filter::keying::ChromaKey>()?;
    registry.register::<filter::keying::InRange>()?;
    registry.register::<filter::histogram::Equalize>()?;
    registry.register::<filter::histogram::Clahe>()?;
    registry.register::<analyze::histogram::Histogram>()?;
    registry.register::<segment::background::Background>()?;
    registry.register::<segment::graph_cut::GraphCut>()?;
    registry.register::<io::read_image::ReadImage>()?;
    registry.register::<io::write_image::WriteImage>()?;
    registry.register::<io::read_correspondences::ReadCorrespondences>()?;
    registry.register::<io::read_camera::ReadCamera>()?;
    registry.register::<io::read_bal::ReadBal>()?;
    registry.register::<io::read_colmap::ReadColmap>()?;
    registry.register::<io::read_poses::ReadPoses>()?;
    registry.register::<io::read_mesh::ReadMesh>()?;
    registry.register::<io::write_mesh::WriteMesh>()?;
    registry.register::<io::read_scene::ReadScene>()?;
    registry.register::<optimize::affine_init::AffineInit>()?;
    registry.register::<render::raycast::BuildBvh>()?;
    registry.register::<render::raycast::Raycast>()?;
    registry.register::<render::raster::Rasterize>()?;
    registry.register::<render::mesh_scene::MeshScene>()?;
    registry.register::<render::points::RenderPoints>()?;
    registry.register::<render::trace::Trace>()?;
    registry.register::<optimize::bundle_adjust::BundleAdjust>()?;
    registry.register::<optimize::synthetic::SyntheticScene>()?;
    registry.register::<geometry::two_view::FindHomography>()?;
    registry.register::<geometry::two_view::FindFundamental>()?;
    registry.register::<geometry::two_view::MatchedPoints>()?;
    registry.register::<geometry::two_view::SelectModel>()?;
    registry.register::<geometry::stitch::StitchPanorama>()?;
    registry.register::<geometry::relative_pose::FindEssential>()?;
    registry.register::<geometry::relative_pose::RelativePoseOp>()?;
    registry.register::<segment::components::Components>()?;
    registry.register::<segment::region_grow::RegionGrow>()?;
    registry.register::<segment::watershed::Watershed>()?;
    registry.register::<segment::kmeans::Kmeans>()?;
    registry.register::<matching::brute_force::BruteForce>()?;
    registry.register::<matching::approximate::Approximate>()?;
    registry.register::<matching::patch::PatchMatch>()?;
    registry.register::<matching::draw::DrawMatches>()?;
    registry.register::<analyze::match_accuracy::MatchAccuracy>()?;
    registry.register::<analyze::homography_error::HomographyError>()?;
    registry.register::<analyze::reconstruction_error::ReconstructionError>()?;
    registry.register::<analyze::reconstruction_points::ReconstructionPoints>()?;
    registry.register::<geometry::calibrate::Calibrate>()?;
    registry.register::<geometry::projection::CalibrateDlt>()?;
    registry.register::<geometry::rectify::Undistort>()?;
    registry.register::<geometry::rectify::StereoRectify>()?;
    registry.register::<geometry::rectify::DisparityToDepth>()?;
    registry.register::<geometry::essential::DecomposeEssential>()?;
    registry.register::<geometry::decompose::DecomposeHomography>()?;
    registry.register::<geometry::pnp::SolvePnp>()?;
    registry.register::<geometry::triangulate::Triangulate>()?;
    registry.register::<geometry::servo::VisualServoStep>()?;
    registry.register::<sfm::stereo::Stereo>()?;
    registry.register::<sfm::depth::DepthToPoints>()?;
    registry.register::<sfm::align::Align>()?;
    registry.register::<sfm::dense::DenseDepth>()?;
    registry.register::<analyze::disparity_error::DisparityError>()?;
    registry.register::<mesh::pointcloud::VoxelDownsample>()?;
    registry.register::<mesh::pointcloud::RemoveOutliers>()?;
    registry.register::<mesh::pointcloud::EstimateNormals>()?;
    registry.register::<mesh::icp::Icp>()?;
    registry.register::<mesh::icp::Transform>()?;
    registry.register::<mesh::fit::FitPrimitive>()?;
    // Surface reconstruction: point-cloud input and screened Poisson.
    registry.register::<io::read_point_cloud::ReadPointCloud>()?;
    registry.register::<mesh::poisson::Poisson>()?;
    // Mesh processing: normals, tangents, subdivision, simplification, measurements, smoothing.
    registry.register::<mesh::normals::Normals>()?;
    registry.register::<mesh::tangents::Tangents>()?;
    registry.register::<mesh::subdivide::Subdivide>()?;
    registry.register::<mesh::simplify::Simplify>()?;
    registry.register::<mesh::metrics::Measure>()?;
    registry.register::<mesh::metrics::Distance>()?;
    registry.register::<mesh::smooth::Smooth>()?;
    registry.register::<mesh::hull::ConvexHull>()?;
    registry.register::<mesh::delaunay::Delaunay2d>()?;
    registry.register::<mesh::depth_mesh::FromDepth>()?;
    registry.register::<mesh::tsdf::TsdfFusion>()?;
    registry.register::<mesh::deform::Deform>()?;
    // Decomposition, learning, sensor simulation, synthesis and compression: each family
    // registers its own operators.
    analyze::register_decomposition(registry)?;
    learn::register(registry)?;
    sensor::register(registry)?;
    texture::register(registry)?;
    video::register_codec(registry)?;
    sfm::register_visual_hull(registry)?;
    Ok(())
}

/// A registry holding every built-in operator.
pub fn builtin_registry() -> Result<Registry, RegistryError> {
    let mut registry = Registry::new();
    register_builtins(&mut registry)?;
    Ok(registry)
}
