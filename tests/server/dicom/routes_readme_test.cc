// The routes-file example of server/README.md, parsed by the server's own parser: the
// documented format and the code cannot drift apart unnoticed.
#include <fstream>
#include <sstream>

#include "gtest/gtest.h"
#include "server/dicom/dicom_routes.h"

namespace decima::server {
namespace {

// The first ```json block after the "### Routes file" heading of server/README.md.
std::string ReadmeRoutesExample() {
  std::ifstream in(std::string(DECIMA_SOURCE_DIR) + "/server/README.md");
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string text = ss.str();
  const size_t heading = text.find("### Routes file");
  if (heading == std::string::npos) return "";
  const size_t open = text.find("```json\n", heading);
  if (open == std::string::npos) return "";
  const size_t start = open + 8;
  const size_t close = text.find("\n```", start);
  return close == std::string::npos ? "" : text.substr(start, close - start);
}

TEST(RoutesReadme, TheExampleParsesAndRoutesAsItsTextSays) {
  const std::string example = ReadmeRoutesExample();
  ASSERT_FALSE(example.empty()) << "no ```json block under '### Routes file' in server/README.md";
  auto routes = ParseDicomRoutes(example, "server/README.md");
  ASSERT_TRUE(routes.ok()) << routes.status();
  ASSERT_EQ(routes->routes.size(), 3u);
  EXPECT_TRUE(routes->refuse_unknown_calling_ae);

  const DicomRoute* orthanc = routes->Match("ORTHANC", "DECIMA");
  ASSERT_NE(orthanc, nullptr);
  EXPECT_EQ(orthanc->name, "ct-head-to-orthanc");
  EXPECT_EQ(orthanc->spec.regions(), 3);
  EXPECT_DOUBLE_EQ(orthanc->spec.target_reduction(), 0.5);
  EXPECT_EQ(orthanc->spec.views_size(), 2);
  EXPECT_EQ(orthanc->destination.host, "127.0.0.1");
  EXPECT_EQ(orthanc->destination.port, 4242);
  EXPECT_EQ(orthanc->destination.aet, "ORTHANC");

  const DicomRoute* mri = routes->Match("MR_SCANNER", "DECIMA");
  ASSERT_NE(mri, nullptr);
  EXPECT_EQ(mri->name, "mri-to-stow");
  EXPECT_EQ(mri->destination.stow_url, "https://pacs.example.org/dicom-web/studies");
  EXPECT_EQ(mri->destination.username, "decima");
  EXPECT_EQ(mri->destination.timeout_seconds, 120);

  // The catch-all route takes every other sender, with no destination.
  const DicomRoute* other = routes->Match("SOMEONE", "DECIMA");
  ASSERT_NE(other, nullptr);
  EXPECT_EQ(other->name, "any-other-sender-no-results");
  EXPECT_FALSE(other->destination.configured());
}

// The README says a misspelt key is refused by name: hold it to that.
TEST(RoutesReadme, AMisspeltKeyInTheExampleIsRefusedByName) {
  std::string example = ReadmeRoutesExample();
  const size_t at = example.find("\"calling_ae\"");
  ASSERT_NE(at, std::string::npos);
  example.replace(at, 12, "\"calling_aet\"");
  auto routes = ParseDicomRoutes(example, "routes.json");
  ASSERT_FALSE(routes.ok());
  EXPECT_NE(std::string(routes.status().message()).find("routes[0].calling_aet"), std::string::npos)
      << routes.status();
}

}  // namespace
}  // namespace decima::server
