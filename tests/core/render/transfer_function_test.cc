#include "core/render/transfer_function.h"

#include <gtest/gtest.h>

#include <fstream>
#include <string>

#include "tests/testing/test_data.h"

namespace decima {
namespace {

void ExpectError(absl::string_view json, const std::string& words,
                 const ScalarRange& range = {0, 100}) {
  auto tf = ParseTransferFunction(json, range, "tf.json");
  ASSERT_FALSE(tf.ok()) << json;
  EXPECT_EQ(tf.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(tf.status().message().find("tf.json"), std::string::npos) << tf.status();
  EXPECT_NE(tf.status().message().find(words), std::string::npos) << tf.status();
}

TEST(TransferFunction, EvaluatesLinearlyBetweenPointsAndClampsOutside) {
  const TransferFunction tf{"t", {{0, {0, 0, 0}, 0}, {10, {1, 0.5f, 0}, 2}, {20, {0, 1, 1}, 4}}};
  float rgb[3], o;
  tf.Evaluate(5, rgb, &o);
  EXPECT_FLOAT_EQ(rgb[0], 0.5f);
  EXPECT_FLOAT_EQ(rgb[1], 0.25f);
  EXPECT_FLOAT_EQ(o, 1);
  tf.Evaluate(15, rgb, &o);
  EXPECT_FLOAT_EQ(rgb[0], 0.5f);
  EXPECT_FLOAT_EQ(o, 3);
  tf.Evaluate(-50, rgb, &o);
  EXPECT_FLOAT_EQ(o, 0);
  tf.Evaluate(1e9, rgb, &o);
  EXPECT_FLOAT_EQ(o, 4);
  EXPECT_FLOAT_EQ(rgb[2], 1);
}

TEST(TransferFunction, CtPresetMakesBoneOpaqueAndAirTransparent) {
  for (double offset : {0.0, 1024.0}) {
    // The shared CT heads are stored as HU + 1024 (no negative values).
    const ScalarRange range{offset == 0 ? -1024.0 : 0.0, offset + 2000};
    auto tf = TransferFunctionPreset("ct", range);
    ASSERT_TRUE(tf.ok()) << tf.status();
    ASSERT_TRUE(tf->Validate().ok());
    float rgb[3], air, soft, bone;
    tf->Evaluate(offset - 1000, rgb, &air);
    tf->Evaluate(offset + 40, rgb, &soft);
    tf->Evaluate(offset + 1000, rgb, &bone);
    EXPECT_EQ(air, 0);
    EXPECT_GT(soft, 0);
    EXPECT_GT(bone, 10 * soft);
    EXPECT_GT(rgb[0], 0.9f);  // bone is bright
  }
}

TEST(TransferFunction, MriT1PresetFollowsTheDataRange) {
  auto tf = TransferFunctionPreset("mri-t1", {100, 1100});
  ASSERT_TRUE(tf.ok()) << tf.status();
  EXPECT_EQ(tf->points.front().value, 100);
  EXPECT_EQ(tf->points.back().value, 1100);
  float rgb[3], bg, wm;
  tf->Evaluate(120, rgb, &bg);
  tf->Evaluate(750, rgb, &wm);
  EXPECT_EQ(bg, 0);
  EXPECT_GT(wm, 0);
  EXPECT_FALSE(TransferFunctionPreset("mri-t1", {5, 5}).ok());
  EXPECT_FALSE(TransferFunctionPreset("mri-t1", {0, std::nan("")}).ok());
}

TEST(TransferFunction, UnknownPresetListsTheKnownOnes) {
  auto tf = TransferFunctionPreset("pet", {0, 1});
  ASSERT_FALSE(tf.ok());
  EXPECT_NE(tf.status().message().find("mri-t1"), std::string::npos);
}

TEST(TransferFunction, JsonRoundTripsAndRelativeDomainMapsOntoTheRange) {
  auto ct = TransferFunctionPreset("ct", {-1024, 3000});
  ASSERT_TRUE(ct.ok());
  auto back = ParseTransferFunction(TransferFunctionToJson(*ct), {0, 1});
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->points.size(), ct->points.size());
  for (size_t i = 0; i < ct->points.size(); ++i) {
    EXPECT_EQ(back->points[i].value, ct->points[i].value);
    EXPECT_EQ(back->points[i].rgb, ct->points[i].rgb);
    EXPECT_EQ(back->points[i].opacity, ct->points[i].opacity);
  }
  auto rel = ParseTransferFunction(
      R"({"name": "r", "domain": "relative", "points": [
            {"value": 0, "rgb": [0, 0, 0], "opacity": 0},
            {"value": 0.5, "rgb": [1, 1, 1], "opacity": 1}]})",
      {200, 400});
  ASSERT_TRUE(rel.ok()) << rel.status();
  EXPECT_EQ(rel->name, "r");
  EXPECT_EQ(rel->points[1].value, 300);
}

TEST(TransferFunction, BadJsonGivesErrorsNamingTheFileAndField) {
  ExpectError("", "not valid JSON");
  ExpectError("{\"points\": [", "not valid JSON");
  ExpectError("points: 1", "not valid JSON");
  ExpectError("[1, 2]", "expected a JSON object");
  ExpectError("{}", "missing key 'points'");
  ExpectError(R"({"points": {}})", "'points' must be an array");
  ExpectError(R"({"points": []})", "expected 1..256");
  ExpectError(R"({"points": [3]})", "points[0] must be an object");
  ExpectError(R"({"points": [{"rgb": [0, 0, 0], "opacity": 0}]})", "missing key 'value'");
  ExpectError(R"({"points": [{"value": 1, "opacity": 0}]})", "missing key 'rgb'");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, 0, 0]}]})", "missing key 'opacity'");
  ExpectError(R"({"points": [{"value": "1", "rgb": [0, 0, 0], "opacity": 0}]})",
              "'value' must be a number");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, 0], "opacity": 0}]})",
              "'rgb' must be an array of 3 numbers");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, "a", 0], "opacity": 0}]})",
              "'rgb' must be an array of 3 numbers");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, 2, 0], "opacity": 0}]})",
              "rgb components must be in 0..1");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, 0, 0], "opacity": true}]})",
              "'opacity' must be a number");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, 0, 0], "opacity": -1}]})",
              "opacity must be finite and >= 0");
  ExpectError(R"({"points": [{"value": 1, "rgb": [0, 0, 0], "opacity": 1e300}]})",
              "opacity must be finite");
  ExpectError(R"({"points": [{"value": 1e999, "rgb": [0, 0, 0], "opacity": 1}]})", "");
  ExpectError(R"({"points": [{"value": 5, "rgb": [0, 0, 0], "opacity": 0},
                             {"value": 5, "rgb": [0, 0, 0], "opacity": 0}]})",
              "is not greater than the previous");
  ExpectError(R"({"points": [{"value": 5, "rgb": [0, 0, 0], "opacity": 0},
                             {"value": 1, "rgb": [0, 0, 0], "opacity": 0}]})",
              "point 1: value 1 is not greater than the previous 5");
  ExpectError(R"({"name": 3, "points": [{"value": 1, "rgb": [0, 0, 0], "opacity": 0}]})",
              "'name' must be a string");
  ExpectError(R"({"domain": "log", "points": [{"value": 1, "rgb": [0, 0, 0], "opacity": 0}]})",
              "'domain' must be");
  ExpectError(R"({"domain": "relative", "points": [{"value": 1, "rgb": [0, 0, 0], "opacity": 0}]})",
              "relative domain needs a non-empty data range", {3, 3});
  std::string many = R"({"points": [)";
  for (int i = 0; i < 300; ++i) {
    many += std::string(i ? "," : "") + R"({"value": )" + std::to_string(i) +
            R"(, "rgb": [0, 0, 0], "opacity": 0})";
  }
  ExpectError(many + "]}", "has 300 entries, expected 1..256");
}

TEST(TransferFunction, LoadRejectsMissingHugeAndEmptyFiles) {
  const auto dir = testing::MakeScratchDir("tf");
  auto missing = LoadTransferFunction(dir / "nope.json", {0, 1});
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);

  const auto empty = dir / "empty.json";
  std::ofstream(empty).close();
  auto e = LoadTransferFunction(empty, {0, 1});
  ASSERT_FALSE(e.ok());
  EXPECT_NE(e.status().message().find("empty.json"), std::string::npos) << e.status();

  const auto huge = dir / "huge.json";
  {
    std::ofstream out(huge);
    out << "{\"points\": [" << std::string(2 << 20, ' ') << "]}";
  }
  auto h = LoadTransferFunction(huge, {0, 1});
  ASSERT_FALSE(h.ok());
  EXPECT_NE(h.status().message().find("larger than 1 MiB"), std::string::npos) << h.status();

  EXPECT_FALSE(LoadTransferFunction(dir, {0, 1}).ok());  // a directory

  const auto good = dir / "good.json";
  {
    std::ofstream out(good);
    out << R"({"points": [{"value": 0, "rgb": [1, 0, 0], "opacity": 0.5}]})";
  }
  auto g = LoadTransferFunction(good, {0, 1});
  ASSERT_TRUE(g.ok()) << g.status();
  EXPECT_EQ(g->points.size(), 1u);
}

}  // namespace
}  // namespace decima
