#include "core/render/renderer.h"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "core/io/volume_io.h"
#include "core/render/diff.h"
#include "core/volume/phantom.h"
#include "tests/core/render/render_test_util.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

using testing::MeshOf;
using testing::RampVolume;
using testing::ReferenceRay;

// A transfer function whose colour and extinction both vary over [0, 100] (so a field change
// shows in the colour), moderately transparent so the whole depth contributes.
TransferFunction RampTf() {
  return {"ramp",
          {{0, {0.1f, 0.2f, 0.9f}, 0.02f},
           {50, {0.9f, 0.6f, 0.1f}, 0.08f},
           {100, {1.0f, 1.0f, 1.0f}, 0.15f}}};
}

Camera ViewCamera(const std::string& view, const Bounds& b, int size, bool perspective) {
  auto dir = ParseView(view);
  EXPECT_TRUE(dir.ok()) << dir.status();
  ViewOptions o;
  o.width = o.height = size;
  o.perspective = perspective;
  auto cam = MakeViewCamera(*dir, b, o);
  EXPECT_TRUE(cam.ok()) << cam.status();
  return *cam;
}

TEST(Render, ConstantFieldCentrePixelFollowsBeerLambert) {
  auto vol = MakeFloatVolume({8, 8, 8}, std::vector<float>(512, 1.0f));
  ASSERT_TRUE(vol.ok());
  const TetMesh mesh = MeshOf(*vol);
  auto cam = MakeViewCamera({0, 0}, MeshBounds(mesh), {.width = 32, .height = 32});
  ASSERT_TRUE(cam.ok());
  TransferFunction tf{"const", {{0, {1, 0.5f, 0.25f}, 0.1f}}};
  auto img = Render(mesh, *cam, tf);
  ASSERT_TRUE(img.ok()) << img.status();
  EXPECT_FALSE(img->empty);
  EXPECT_EQ(img->stats.lost_rays, 0);
  EXPECT_EQ(img->stats.fallback_steps, 0);
  // Centre pixel: 7 mm of constant extinction 0.1/mm.
  const int64_t c = 16 * 32 + 16;
  EXPECT_NEAR(img->alpha[c], 1 - std::exp(-0.7), 1e-5);
  EXPECT_NEAR(img->rgb[3 * c], 1 - std::exp(-0.7), 1e-5);
  EXPECT_NEAR(img->rgb[3 * c + 1], 0.5 * (1 - std::exp(-0.7)), 1e-5);
}

// The unsimplified mesh of a ramp phantom against an independent slab integration of the voxel
// field (trilinear, equal to the 5-tet linear interpolation for a linear field). Golden
// tolerance: 2e-4 per colour channel and alpha (0..1), i.e. 1/20 of an 8-bit level; measured
// 0.6e-5..2.6e-5 (renderer: midpoint sub-samples 0.1 mm apart, float; reference: 2000 samples).
struct ReferenceCase {
  const char* view;
  bool perspective;
};

class RenderMatchesReference : public ::testing::TestWithParam<ReferenceCase> {};

TEST_P(RenderMatchesReference, RampPhantom) {
  const Volume vol = RampVolume({7, 6, 5}, {5, 9, 4, 6});
  const TetMesh mesh = MeshOf(vol);
  const Bounds b = MeshBounds(mesh);
  const Camera cam = ViewCamera(GetParam().view, b, 32, GetParam().perspective);
  const TransferFunction tf = RampTf();
  RenderOptions opt;
  opt.step_mm = 0.1;
  opt.min_transmittance = 0;  // compare the full integral
  auto img = Render(mesh, cam, tf, opt);
  ASSERT_TRUE(img.ok()) << img.status();
  EXPECT_EQ(img->stats.lost_rays, 0);

  auto field = [&](const Eigen::Vector3d& p) { return testing::Trilinear(vol, p); };
  double worst = 0;
  int hits = 0, skipped = 0;
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      // Rays grazing the silhouette (within 0.02 px) are decided by the renderer's tie-breaking;
      // skip them, and check that they are few.
      if (testing::NearSilhouette(cam, x, y, {{b.min, b.max}})) {
        ++skipped;
        continue;
      }
      const auto ref = ReferenceRay(cam, x, y, b.min, b.max, field, tf);
      hits += ref.hit;
      const int64_t p = int64_t{y} * cam.width + x;
      for (int c = 0; c < 3; ++c)
        worst = std::max(worst, std::abs(img->rgb[3 * p + c] - ref.rgb[c]));
      worst = std::max(worst, std::abs(img->alpha[p] - ref.alpha));
    }
  }
  EXPECT_GT(hits, 250);
  EXPECT_LT(skipped, hits / 10);
  EXPECT_LT(worst, 2e-4) << "largest channel difference from the reference";
}

INSTANTIATE_TEST_SUITE_P(Views, RenderMatchesReference,
                         ::testing::Values(ReferenceCase{"anterior", false},
                                           ReferenceCase{"superior", false},
                                           ReferenceCase{"30,20", false},
                                           ReferenceCase{"oblique", true},
                                           ReferenceCase{"-120,-35", true}),
                         [](const auto& info) {
                           std::string n = info.param.view;
                           for (char& c : n)
                             if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
                           return n + (info.param.perspective ? "_perspective" : "_orthographic");
                         });

// A tunnel along x through the ramp block makes the mesh non-convex: rays along y leave the mesh
// and re-enter it. The reference integrates the block minus the tunnel. Tolerance 1e-3
// (measured 1e-4: the reference's 3000 samples resolve the tunnel walls to 1/3000 of the ray).
TEST(Render, NonConvexMeshRaysReenterAfterAGap) {
  const Volume vol = RampVolume({6, 8, 7}, {5, 9, 4, 6}, {1, 1, 1}, {0, 0, 0});
  TetMesh full = MeshOf(vol);
  const Eigen::Vector3d tlo(-1, 3, 2), thi(10, 5, 4);  // cubes j in [3,5), k in [2,4), all i
  auto in_tunnel = [&](const Eigen::Vector3d& p) {
    return (p.array() > tlo.array()).all() && (p.array() < thi.array()).all();
  };
  TetMesh mesh = full;
  mesh.tets.clear();
  for (int64_t t = 0; t < full.tet_count(); ++t) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int q = 0; q < 4; ++q) c += full.Position(full.tets[4 * t + q]) / 4;
    if (!in_tunnel(c)) mesh.tets.insert(mesh.tets.end(), &full.tets[4 * t], &full.tets[4 * t + 4]);
  }
  ASSERT_LT(mesh.tet_count(), full.tet_count());
  const Bounds b = MeshBounds(full);
  for (const char* view : {"anterior", "20,10"}) {
    SCOPED_TRACE(view);
    const Camera cam = ViewCamera(view, b, 24, false);
    const TransferFunction tf = RampTf();
    RenderOptions opt;
    opt.step_mm = 0.1;
    opt.min_transmittance = 0;
    auto img = Render(mesh, cam, tf, opt);
    ASSERT_TRUE(img.ok()) << img.status();
    EXPECT_EQ(img->stats.lost_rays, 0);
    auto field = [&](const Eigen::Vector3d& p) {
      return in_tunnel(p) ? std::nan("") : testing::Trilinear(vol, p);
    };
    double worst = 0;
    int64_t checked = 0;
    for (int y = 0; y < cam.height; ++y) {
      for (int x = 0; x < cam.width; ++x) {
        // Skip rays near the outer or the tunnel silhouette.
        if (testing::NearSilhouette(cam, x, y, {{b.min, b.max}, {tlo, thi}}, 0.05)) continue;
        const auto ref = ReferenceRay(cam, x, y, b.min, b.max, field, tf, 3000);
        ++checked;
        const int64_t p = int64_t{y} * cam.width + x;
        worst = std::max(worst, std::abs(img->alpha[p] - ref.alpha));
        for (int c = 0; c < 3; ++c)
          worst = std::max(worst, std::abs(img->rgb[3 * p + c] - ref.rgb[c]));
      }
    }
    EXPECT_GT(checked, 150);
    EXPECT_LT(worst, 1e-3);
  }
}

// A transfer function that is transparent on the middle of the ramp: the tets there are
// skipped (empty-space skipping), rays stop at the gap and continue behind it through a later
// entry face; the image still matches the reference integral (same tolerance as above).
TEST(Render, TransparentValueRangeIsSkippedAndRaysContinueBehindIt) {
  const Volume vol = RampVolume({8, 7, 6}, {0, 3, 9, 2});
  const TetMesh mesh = MeshOf(vol);
  const Bounds b = MeshBounds(mesh);
  const TransferFunction tf{"gap",
                            {{0, {0.2f, 0.4f, 0.9f}, 0.05f},
                             {15, {0.3f, 0.5f, 0.8f}, 0.05f},
                             {25, {0, 0, 0}, 0},
                             {45, {0, 0, 0}, 0},
                             {55, {1, 0.8f, 0.2f}, 0.1f},
                             {120, {1, 1, 1}, 0.2f}}};
  for (const char* view : {"anterior", "oblique"}) {
    SCOPED_TRACE(view);
    const Camera cam = ViewCamera(view, b, 24, std::string(view) == "oblique");
    RenderOptions opt;
    opt.step_mm = 0.1;
    opt.min_transmittance = 0;
    auto img = Render(mesh, cam, tf, opt);
    ASSERT_TRUE(img.ok()) << img.status();
    EXPECT_GT(img->stats.visible_tets, 0);
    EXPECT_LT(img->stats.visible_tets, mesh.tet_count());
    EXPECT_EQ(img->stats.lost_rays, 0);
    auto field = [&](const Eigen::Vector3d& p) { return testing::Trilinear(vol, p); };
    double worst = 0;
    int64_t checked = 0;
    for (int y = 0; y < cam.height; ++y) {
      for (int x = 0; x < cam.width; ++x) {
        if (testing::NearSilhouette(cam, x, y, {{b.min, b.max}})) continue;
        const auto ref = ReferenceRay(cam, x, y, b.min, b.max, field, tf);
        ++checked;
        const int64_t p = int64_t{y} * cam.width + x;
        worst = std::max(worst, std::abs(img->alpha[p] - ref.alpha));
        for (int c = 0; c < 3; ++c)
          worst = std::max(worst, std::abs(img->rgb[3 * p + c] - ref.rgb[c]));
      }
    }
    EXPECT_GT(checked, 150);
    EXPECT_LT(worst, 2e-4);
  }
}

TEST(Render, SameMeshTwiceGivesZeroDiff) {
  const TetMesh mesh = MeshOf(RampVolume({6, 6, 6}, {0, 7, 5, 3}));
  const Camera cam = ViewCamera("oblique", MeshBounds(mesh), 48, true);
  auto a = Render(mesh, cam, RampTf());
  auto b = Render(mesh, cam, RampTf());
  ASSERT_TRUE(a.ok() && b.ok());
  auto d = Diff(*a, *b);
  ASSERT_TRUE(d.ok()) << d.status();
  EXPECT_EQ(d->diff1, 0.0);
  EXPECT_EQ(d->max_diff2, 0.0);
  EXPECT_EQ(d->changed_pixels, 0);
  EXPECT_FALSE(a->empty);
}

// Point-in-triangle with a tiny tolerance (pixels).
bool InTriangle(const Eigen::Vector2d& p, const Eigen::Vector2d& a, const Eigen::Vector2d& b,
                const Eigen::Vector2d& c) {
  auto cross = [](const Eigen::Vector2d& u, const Eigen::Vector2d& v) {
    return u.x() * v.y() - u.y() * v.x();
  };
  const double area = cross(b - a, c - a);
  if (area == 0) return false;
  const double s = area > 0 ? 1 : -1, eps = 1e-6 * std::abs(area);
  return s * cross(b - a, p - a) >= -eps && s * cross(c - b, p - b) >= -eps &&
         s * cross(a - c, p - c) >= -eps;
}

TEST(Render, ChangedVertexChangesOnlyPixelsWhereItsTetsProject) {
  const TetMesh mesh = MeshOf(RampVolume({7, 7, 7}, {0, 5, 3, 4}, {1, 1, 1}, {0, 0, 0}));
  // An interior vertex (3, 3, 3).
  const int32_t v = 3 + 7 * (3 + 7 * 3);
  TetMesh changed = mesh;
  changed.scalars[v] += 60;
  for (bool perspective : {false, true}) {
    SCOPED_TRACE(perspective ? "perspective" : "orthographic");
    const Camera cam = ViewCamera("25,15", MeshBounds(mesh), 64, perspective);
    auto a = Render(mesh, cam, RampTf());
    auto b = Render(changed, cam, RampTf());
    ASSERT_TRUE(a.ok() && b.ok());
    auto d = Diff(*a, *b);
    ASSERT_TRUE(d.ok());
    EXPECT_GT(d->diff1, 0);
    EXPECT_GT(d->changed_pixels, 10);

    // Union of the projections of the tets incident to v: each tet projects to the union of
    // the four triangles of its projected vertices.
    std::vector<std::array<Eigen::Vector2d, 4>> tets;
    for (int64_t t = 0; t < mesh.tet_count(); ++t) {
      const int32_t* q = &mesh.tets[4 * t];
      if (std::find(q, q + 4, v) == q + 4) continue;
      std::array<Eigen::Vector2d, 4> p;
      for (int k = 0; k < 4; ++k) p[k] = cam.Project(mesh.Position(q[k])).head<2>();
      tets.push_back(p);
    }
    ASSERT_FALSE(tets.empty());
    int64_t outside = 0;
    for (int y = 0; y < cam.height; ++y) {
      for (int x = 0; x < cam.width; ++x) {
        if (d->diff2[int64_t{y} * cam.width + x] == 0) continue;
        const Eigen::Vector2d px(x, y);
        bool inside = false;
        for (const auto& p : tets) {
          inside |= InTriangle(px, p[0], p[1], p[2]) || InTriangle(px, p[0], p[1], p[3]) ||
                    InTriangle(px, p[0], p[2], p[3]) || InTriangle(px, p[1], p[2], p[3]);
        }
        if (!inside) ++outside;
      }
    }
    EXPECT_EQ(outside, 0) << "pixels changed outside the projection of the vertex's tets";
  }
}

TEST(Render, FullyTransparentTransferFunctionGivesBackground) {
  const TetMesh mesh = MeshOf(RampVolume({5, 5, 5}, {0, 10, 10, 10}));
  const TransferFunction tf{"clear", {{0, {1, 1, 1}, 0}, {100, {1, 0, 0}, 0}}};
  RenderOptions opt;
  opt.background = {0.25f, 0.5f, 0.75f};
  for (bool perspective : {false, true}) {
    const Camera cam = ViewCamera("oblique", MeshBounds(mesh), 24, perspective);
    auto img = Render(mesh, cam, tf, opt);
    ASSERT_TRUE(img.ok()) << img.status();
    EXPECT_TRUE(img->empty);  // nothing visible: flagged
    EXPECT_EQ(img->stats.visible_tets, 0);
    for (int64_t p = 0; p < int64_t{cam.width} * cam.height; ++p) {
      ASSERT_EQ(img->alpha[p], 0.0f);
      ASSERT_EQ(img->rgb[3 * p + 0], 0.25f);
      ASSERT_EQ(img->rgb[3 * p + 1], 0.5f);
      ASSERT_EQ(img->rgb[3 * p + 2], 0.75f);
    }
  }
}

TEST(Render, CameraLookingAwayGivesExplicitEmptyImage) {
  const TetMesh mesh = MeshOf(RampVolume({5, 5, 5}, {0, 10, 10, 10}));
  const Bounds b = MeshBounds(mesh);
  RenderOptions opt;
  opt.background = {0.1f, 0.2f, 0.3f};
  for (bool perspective : {false, true}) {
    Camera cam = ViewCamera("anterior", b, 16, perspective);
    // Turn around: the whole mesh is behind the camera.
    cam.forward = -cam.forward;
    cam.right = -cam.right;
    auto img = Render(mesh, cam, RampTf(), opt);
    ASSERT_TRUE(img.ok()) << img.status();
    EXPECT_TRUE(img->empty);
    EXPECT_EQ(img->stats.rays_hit, 0);
    EXPECT_EQ(img->rgb[0], 0.1f);
    EXPECT_EQ(img->alpha[0], 0.0f);
  }
}

TEST(Render, MeshBesideTheViewGivesExplicitEmptyImage) {
  const TetMesh mesh = MeshOf(RampVolume({5, 5, 5}, {0, 10, 10, 10}));
  for (bool perspective : {false, true}) {
    Camera cam = ViewCamera("anterior", MeshBounds(mesh), 16, perspective);
    cam.eye += 1000 * cam.right;  // in front of the camera, but far outside the frame
    auto img = Render(mesh, cam, RampTf());
    ASSERT_TRUE(img.ok()) << img.status();
    EXPECT_TRUE(img->empty);
  }
}

TEST(Render, CameraInsideTheMeshIsAClearError) {
  const TetMesh mesh = MeshOf(RampVolume({5, 5, 5}, {0, 10, 10, 10}));
  Camera cam = ViewCamera("anterior", MeshBounds(mesh), 16, true);
  cam.eye = MeshBounds(mesh).Center();
  auto img = Render(mesh, cam, RampTf());
  ASSERT_FALSE(img.ok());
  EXPECT_EQ(img.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(img.status().message().find("behind the camera"), std::string::npos) << img.status();
}

TEST(Render, BadCameraAndOptionsAreClearErrors) {
  const TetMesh mesh = MeshOf(RampVolume({4, 4, 4}, {0, 10, 10, 10}));
  const Camera good = ViewCamera("anterior", MeshBounds(mesh), 16, false);
  Camera cam = good;
  cam.width = 0;
  EXPECT_EQ(Render(mesh, cam, RampTf()).status().code(), absl::StatusCode::kInvalidArgument);
  cam = good;
  cam.up = cam.forward;
  EXPECT_EQ(Render(mesh, cam, RampTf()).status().code(), absl::StatusCode::kInvalidArgument);
  cam = good;
  cam.ortho_width_mm = std::nan("");
  EXPECT_EQ(Render(mesh, cam, RampTf()).status().code(), absl::StatusCode::kInvalidArgument);
  RenderOptions opt;
  opt.step_mm = 0;
  EXPECT_EQ(Render(mesh, good, RampTf(), opt).status().code(), absl::StatusCode::kInvalidArgument);
  TransferFunction bad = RampTf();
  bad.points[1].value = 200;  // not increasing
  EXPECT_EQ(Render(mesh, good, bad).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(Render, ImageDoesNotDependOnThreadCount) {
  const TetMesh mesh = MeshOf(RampVolume({9, 8, 7}, {0, 5, 3, 4}));
  const Camera cam = ViewCamera("oblique", MeshBounds(mesh), 50, true);
  RenderOptions one, three;
  one.threads = 1;
  three.threads = 3;
  auto a = Render(mesh, cam, RampTf(), one);
  auto b = Render(mesh, cam, RampTf(), three);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->rgb, b->rgb);
  EXPECT_EQ(a->alpha, b->alpha);
  EXPECT_EQ(a->stats.steps, b->stats.steps);
}

TEST(Render, CancelledTokenStopsTheRender) {
  const TetMesh mesh = MeshOf(RampVolume({5, 5, 5}, {0, 10, 10, 10}));
  const Camera cam = ViewCamera("anterior", MeshBounds(mesh), 16, false);
  CancelToken token;
  token.Cancel();
  auto img = Render(mesh, cam, RampTf(), {}, &token);
  EXPECT_EQ(img.status().code(), absl::StatusCode::kCancelled);
}

TEST(BuildRenderableMesh, FindsNeighboursAndBoundary) {
  const TetMesh mesh = MeshOf(RampVolume({3, 3, 3}, {0, 1, 1, 1}));
  auto rm = BuildRenderableMesh(mesh);
  ASSERT_TRUE(rm.ok()) << rm.status();
  EXPECT_EQ(rm->tet_count(), 40);
  // 2x2x2 cubes: 6 box faces of 4 squares, 2 triangles each.
  EXPECT_EQ(rm->boundary_faces.size(), 48u);
  int64_t links = 0;
  for (int64_t t = 0; t < rm->tet_count(); ++t) {
    for (int q = 0; q < 4; ++q) {
      const int32_t n = rm->cells[8 * t + 4 + q];
      if (n < 0) continue;
      ++links;
      // Symmetric.
      bool back = false;
      for (int r = 0; r < 4; ++r) back |= rm->cells[8 * int64_t{n} + 4 + r] == t;
      EXPECT_TRUE(back);
    }
  }
  EXPECT_EQ(links + 48, 4 * 40);
}

// The consuming build (the job's original mesh, issue 30) frees the mesh and gives exactly the
// renderable mesh of the copying build: cells with neighbours, boundary faces with their
// winding (read from the moved positions), bounds and scalar range.
TEST(BuildRenderableMesh, ConsumingBuildIsIdenticalAndEmptiesTheMesh) {
  TetMesh mesh = MeshOf(RampVolume({5, 4, 3}, {0, 1, 1, 1}));
  // Move one interior and one boundary vertex so the windings depend on the positions read.
  mesh.positions[3 * 7 + 1] += 0.2f;
  mesh.positions[0] -= 0.3f;
  auto copied = BuildRenderableMesh(mesh);
  ASSERT_TRUE(copied.ok()) << copied.status();
  auto consumed = BuildRenderableMesh(std::move(mesh));
  ASSERT_TRUE(consumed.ok()) << consumed.status();
  EXPECT_EQ(consumed->positions, copied->positions);
  EXPECT_EQ(consumed->scalars, copied->scalars);
  EXPECT_EQ(consumed->cells, copied->cells);
  EXPECT_EQ(consumed->boundary_faces, copied->boundary_faces);
  EXPECT_EQ(consumed->boundary_vertices, copied->boundary_vertices);
  EXPECT_EQ(consumed->bounds.min, copied->bounds.min);
  EXPECT_EQ(consumed->bounds.max, copied->bounds.max);
  EXPECT_EQ(consumed->scalar_range.min, copied->scalar_range.min);
  EXPECT_EQ(consumed->scalar_range.max, copied->scalar_range.max);
  EXPECT_EQ(mesh.vertex_count(), 0);  // NOLINT(bugprone-use-after-move): the contract
  EXPECT_TRUE(mesh.tets.empty());
  EXPECT_TRUE(mesh.labels.empty());
  EXPECT_TRUE(mesh.positions.empty());
}

TEST(BuildRenderableMesh, RejectsBrokenMeshesWithClearErrors) {
  const TetMesh good = MeshOf(RampVolume({3, 3, 3}, {0, 1, 1, 1}));
  auto expect_error = [](const TetMesh& m, const std::string& words) {
    auto rm = BuildRenderableMesh(m);
    ASSERT_FALSE(rm.ok());
    EXPECT_EQ(rm.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(rm.status().message().find(words), std::string::npos) << rm.status();
  };
  TetMesh m = good;
  m.tets[5] = 1000;
  expect_error(m, "refers to vertex 1000");
  m = good;
  m.tets[5] = m.tets[4];
  expect_error(m, "repeats vertex");
  m = good;
  m.positions[7] = std::nanf("");
  expect_error(m, "non-finite position");
  m = good;
  m.scalars[2] = std::numeric_limits<float>::infinity();
  expect_error(m, "non-finite scalar");
  m = good;
  m.positions.pop_back();
  expect_error(m, "not a mesh");
  m = good;
  m.tets.clear();
  expect_error(m, "not a mesh");
  m = good;
  // A third tet on an interior face.
  m.tets.insert(m.tets.end(), {good.tets[0], good.tets[1], good.tets[2], good.tets[3]});
  expect_error(m, "non-manifold");
}

// A real CT head: every ray is walked to the end (no lost rays), bone shows as bright pixels
// in the middle of an anterior view, and air around the head stays background.
TEST(Render, CtHeadAnteriorShowsBoneAndNoLostRays) {
  // The small head-and-neck CT (64x64x93) keeps this fast under the sanitizers.
  DECIMA_REQUIRE_SHARED_DATA(path, "ct-headneck-64x64x93.nii.gz");
  auto vol = io::ReadVolume(path);
  ASSERT_TRUE(vol.ok()) << vol.status();
  const TetMesh mesh = MeshOf(*vol);
  auto rm = BuildRenderableMesh(mesh);
  ASSERT_TRUE(rm.ok()) << rm.status();
  auto cam = MakeViewCamera({0, 0}, rm->bounds, {.width = 96, .height = 96});
  ASSERT_TRUE(cam.ok());
  auto tf = TransferFunctionPreset("ct", rm->scalar_range);
  ASSERT_TRUE(tf.ok());
  auto img = Render(*rm, *cam, *tf);
  ASSERT_TRUE(img.ok()) << img.status();
  EXPECT_FALSE(img->empty);
  EXPECT_EQ(img->stats.lost_rays, 0);
  EXPECT_LT(img->stats.visible_tets, rm->tet_count());  // air is skipped
  int64_t bright = 0;
  for (int64_t p = 0; p < 96 * 96; ++p) bright += img->rgb[3 * p + 2] > 0.6f;
  EXPECT_GT(bright, 96 * 96 / 20);
  EXPECT_EQ(img->alpha[0], 0.0f);  // corner: outside the head's box
}

// --- cameras -------------------------------------------------------------------------------

TEST(ParseView, KnowsThePresetsAndAzimuthElevation) {
  struct Case {
    const char* name;
    double az, el;
  } cases[] = {{"anterior", 0, 0},   {"Posterior", 180, 0}, {"left", 90, 0},
               {"lateral", 90, 0},   {"right", -90, 0},     {"superior", 0, 90},
               {"inferior", 0, -90}, {"oblique", 45, 30},   {" 30, -15 ", 30, -15}};
  for (const Case& c : cases) {
    auto v = ParseView(c.name);
    ASSERT_TRUE(v.ok()) << c.name << ": " << v.status();
    EXPECT_EQ(v->azimuth_deg, c.az) << c.name;
    EXPECT_EQ(v->elevation_deg, c.el) << c.name;
  }
  for (const char* bad : {"", "front", "30", "30,95", "a,b", "1,2,3", "nan,0"}) {
    auto v = ParseView(bad);
    EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument) << bad;
  }
}

TEST(MakeViewCamera, PresetsPutTheAnatomyWhereRadiologistsExpectIt) {
  Bounds b;
  b.min = {-50, -60, -40};
  b.max = {50, 60, 40};
  const Eigen::Vector3d c = b.Center();
  const Eigen::Vector3d left(40, 0, 0), posterior(0, 50, 0), superior(0, 0, 30);
  auto screen = [&](const char* view, const Eigen::Vector3d& d, bool persp) {
    const Camera cam = ViewCamera(view, b, 100, persp);
    return Eigen::Vector2d(cam.Project(c + d).head<2>() - cam.Project(c).head<2>());
  };
  for (bool persp : {false, true}) {
    // Anterior: patient's left on the image right, head up.
    EXPECT_GT(screen("anterior", left, persp).x(), 10);
    EXPECT_LT(screen("anterior", superior, persp).y(), -10);
    // Posterior: patient's left on the image left.
    EXPECT_LT(screen("posterior", left, persp).x(), -10);
    EXPECT_LT(screen("posterior", superior, persp).y(), -10);
    // Left lateral: posterior on the image right (nose to the left).
    EXPECT_GT(screen("left", posterior, persp).x(), 10);
    EXPECT_LT(screen("right", posterior, persp).x(), -10);
    // Superior: posterior at the top, left on the right.
    EXPECT_LT(screen("superior", posterior, persp).y(), -10);
    EXPECT_GT(screen("superior", left, persp).x(), 10);
    // Inferior: anterior at the top, left on the right (radiological axial convention).
    EXPECT_GT(screen("inferior", posterior, persp).y(), 10);
    EXPECT_GT(screen("inferior", left, persp).x(), 10);
  }
}

TEST(MakeViewCamera, WholeBoxIsInsideTheImageForEveryView) {
  Bounds b;
  b.min = {-10, 3, 100};
  b.max = {90, 43, 170};
  for (const char* view :
       {"anterior", "posterior", "left", "right", "superior", "inferior", "oblique", "137,-61"}) {
    for (bool persp : {false, true}) {
      for (auto [w, h] : {std::pair{64, 64}, std::pair{120, 50}, std::pair{40, 90}}) {
        auto dir = ParseView(view);
        ViewOptions o;
        o.width = w;
        o.height = h;
        o.perspective = persp;
        auto cam = MakeViewCamera(*dir, b, o);
        ASSERT_TRUE(cam.ok());
        for (int k = 0; k < 8; ++k) {
          const Eigen::Vector3d p((k & 1) ? b.max.x() : b.min.x(), (k & 2) ? b.max.y() : b.min.y(),
                                  (k & 4) ? b.max.z() : b.min.z());
          const Eigen::Vector3d s = cam->Project(p);
          EXPECT_GT(s.z(), 0) << view;
          EXPECT_GE(s.x(), -0.5) << view << " " << w << "x" << h;
          EXPECT_LE(s.x(), w - 0.5) << view << " " << w << "x" << h;
          EXPECT_GE(s.y(), -0.5) << view << " " << w << "x" << h;
          EXPECT_LE(s.y(), h - 0.5) << view << " " << w << "x" << h;
        }
      }
    }
  }
}

TEST(MakeViewCamera, RejectsBadOptions) {
  Bounds b;
  b.min = {0, 0, 0};
  b.max = {1, 1, 1};
  EXPECT_FALSE(MakeViewCamera({0, 0}, b, {.width = 0}).ok());
  EXPECT_FALSE(MakeViewCamera({0, 0}, b, {.width = 9000}).ok());
  EXPECT_FALSE(MakeViewCamera({0, 0}, b, {.perspective = true, .fov_y_deg = 180}).ok());
  EXPECT_FALSE(MakeViewCamera({0, 95}, b).ok());
  Bounds empty;
  EXPECT_FALSE(MakeViewCamera({0, 0}, empty).ok());
  Bounds nan = b;
  nan.max.x() = std::nan("");
  EXPECT_FALSE(MakeViewCamera({0, 0}, nan).ok());
}

// The original rendered straight from the grid (RenderableGrid: cells and neighbours computed
// from the cell id) against the same original materialized (Tetrahedralize, RenderableMesh):
// the same floats in every pixel, so the same PNG bytes. A head phantom with noise, odd dims
// (and one flipped, even/odd case), orthographic and perspective views along axes (rays through
// vertices and edges) and oblique; a transfer function transparent on the air (rays enter
// through faces next to invisible tets) and one opaque everywhere (entry through the hull, which
// the mesh takes from its stored hull list and the grid from its neighbours).
TEST(RenderGrid, SamePixelsAsTheMaterializedOriginal) {
  struct Case {
    std::array<int64_t, 3> dims;
    bool flip;
  };
  for (const Case& c : {Case{{23, 19, 15}, false}, Case{{16, 13, 10}, true}}) {
    HeadPhantomOptions po;
    po.dims = c.dims;
    po.spacing = {0.9, 1.1, 1.7};
    po.region_means = {0, 1000, 400};
    po.noise_sigma = 60;
    auto phantom = MakeHeadPhantom(po);
    ASSERT_TRUE(phantom.ok()) << phantom.status();
    Volume& image = phantom->image;
    image.origin = {-11, 7, 3};
    if (c.flip) image.direction.col(1) *= -1;
    auto grid = BuildRenderableGrid(image);
    ASSERT_TRUE(grid.ok()) << grid.status();
    auto mesh = BuildRenderableMesh(MeshOf(image));
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    ASSERT_EQ(grid->tet_count(), mesh->tet_count());
    ASSERT_EQ(grid->positions, mesh->positions);
    ASSERT_EQ(grid->scalars, mesh->scalars);
    ASSERT_EQ(grid->bounds.min, mesh->bounds.min);
    ASSERT_EQ(grid->bounds.max, mesh->bounds.max);
    const TransferFunction air_clear{
        "air clear",
        {{100, {0.2f, 0.3f, 0.9f}, 0}, {400, {0.9f, 0.5f, 0.2f}, 0.08f}, {1000, {1, 1, 1}, 0.3f}}};
    const TransferFunction everywhere{
        "everywhere", {{-200, {0.1f, 0.2f, 0.3f}, 0.01f}, {1200, {1, 0.8f, 0.6f}, 0.1f}}};
    int64_t partly_visible = 0;
    for (const TransferFunction* tf : {&air_clear, &everywhere}) {
      for (const char* view : {"anterior", "superior", "left", "oblique", "-120,-35"}) {
        for (bool perspective : {false, true}) {
          SCOPED_TRACE(::testing::Message()
                       << c.dims[0] << "x" << c.dims[1] << "x" << c.dims[2] << " " << tf->name
                       << " " << view << (perspective ? " perspective" : " ortho"));
          const Camera cam = ViewCamera(view, mesh->bounds, 40, perspective);
          auto from_mesh = Render(*mesh, cam, *tf);
          auto from_grid = Render(*grid, cam, *tf);
          ASSERT_TRUE(from_mesh.ok()) << from_mesh.status();
          ASSERT_TRUE(from_grid.ok()) << from_grid.status();
          ASSERT_FALSE(from_mesh->empty);
          EXPECT_EQ(from_grid->rgb, from_mesh->rgb);
          EXPECT_EQ(from_grid->alpha, from_mesh->alpha);
          EXPECT_EQ(from_grid->ToImage().pixels, from_mesh->ToImage().pixels);
          EXPECT_EQ(from_grid->stats.visible_tets, from_mesh->stats.visible_tets);
          EXPECT_EQ(from_grid->stats.entry_faces, from_mesh->stats.entry_faces);
          EXPECT_EQ(from_grid->stats.steps, from_mesh->stats.steps);
          EXPECT_EQ(from_grid->stats.lost_rays, 0);
          partly_visible += from_mesh->stats.visible_tets < mesh->tet_count();
        }
      }
    }
    EXPECT_GT(partly_visible, 0);  // the air-clear function did skip tets
  }
}

TEST(RenderGrid, RefusesAGridTooThinOrNotFinite) {
  auto thin = MakeFloatVolume({5, 1, 4}, std::vector<float>(20, 1.0f));
  ASSERT_TRUE(thin.ok());
  auto r = BuildRenderableGrid(*thin);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("at least 2 voxels"), std::string::npos) << r.status();

  std::vector<float> values(27, 1.0f);
  values[13] = std::nanf("");
  auto nan = MakeFloatVolume({3, 3, 3}, values);
  ASSERT_TRUE(nan.ok());
  r = BuildRenderableGrid(*nan);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("voxel 13"), std::string::npos) << r.status();
}

}  // namespace
}  // namespace decima
