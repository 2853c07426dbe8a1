// The table of bad job specs shared by the JobSpecFromProto unit test and the CreateJob handler
// test: each case changes a valid spec in one way and names the field the error must name.
#pragma once

#include <cmath>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "decima/v1/jobs.pb.h"

namespace decima::server {

struct BadJobSpec {
  std::string name;
  std::string field;  // the error message starts with "<field>:"
  std::function<void(v1::JobSpec*)> mutate;
};

inline std::vector<BadJobSpec> BadJobSpecs() {
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  constexpr double kInf = std::numeric_limits<double>::infinity();
  using S = v1::JobSpec*;
  return {
      {"no volume", "spec.volume", [](S s) { s->clear_volume(); }},
      {"volume not a volume name", "spec.volume", [](S s) { s->set_volume("blobs/abc"); }},
      {"label map with an empty id", "spec.label_map", [](S s) { s->set_label_map("volumes/"); }},
      {"regions 1", "spec.regions", [](S s) { s->set_regions(1); }},
      {"regions 9", "spec.regions", [](S s) { s->set_regions(9); }},
      {"regions explicitly 0", "spec.regions", [](S s) { s->set_regions(0); }},
      {"regions negative", "spec.regions", [](S s) { s->set_regions(-3); }},
      {"class means: 2 for 3 regions", "spec.class_means",
       [](S s) {
         s->add_class_means(1);
         s->add_class_means(2);
       }},
      {"class means: NaN", "spec.class_means",
       [](S s) {
         s->add_class_means(1);
         s->add_class_means(kNaN);
         s->add_class_means(3);
       }},
      {"class means: +inf", "spec.class_means",
       [](S s) {
         s->add_class_means(1);
         s->add_class_means(2);
         s->add_class_means(kInf);
       }},
      {"class means: 1000 values", "spec.class_means",
       [](S s) {
         for (int i = 0; i < 1000; ++i) s->add_class_means(i);
       }},
      {"region names: 2 for 3 regions", "spec.region_names",
       [](S s) {
         s->add_region_names("air");
         s->add_region_names("bone");
       }},
      {"region names: 3 for 4 regions", "spec.region_names",
       [](S s) {
         s->set_regions(4);
         for (const char* n : {"a", "b", "c"}) s->add_region_names(n);
       }},
      {"region names: an empty one", "spec.region_names[1]",
       [](S s) {
         for (const char* n : {"air", "", "bone"}) s->add_region_names(n);
       }},
      {"region names: a duplicate", "spec.region_names[2]",
       [](S s) {
         for (const char* n : {"air", "bone", "Air"}) s->add_region_names(n);
       }},
      {"region names: a control character", "spec.region_names[0]",
       [](S s) {
         for (const char* n : {"a\nb", "brain", "bone"}) s->add_region_names(n);
       }},
      {"region names: 65 bytes", "spec.region_names[2]",
       [](S s) {
         for (const char* n : {"air", "brain"}) s->add_region_names(n);
         s->add_region_names(std::string(65, 'x'));
       }},
      {"region names: 1000 of them", "spec.region_names",
       [](S s) {
         for (int i = 0; i < 1000; ++i) s->add_region_names(std::to_string(i));
       }},
      {"target_reduction NaN", "spec.target_reduction", [](S s) { s->set_target_reduction(kNaN); }},
      {"target_reduction +inf", "spec.target_reduction",
       [](S s) { s->set_target_reduction(kInf); }},
      {"target_reduction -inf", "spec.target_reduction",
       [](S s) { s->set_target_reduction(-kInf); }},
      {"target_reduction negative", "spec.target_reduction",
       [](S s) { s->set_target_reduction(-0.1); }},
      {"target_reduction 1", "spec.target_reduction", [](S s) { s->set_target_reduction(1.0); }},
      {"policy unknown enum 7", "spec.policy",
       [](S s) { s->set_policy(static_cast<v1::SimplifyPolicy>(7)); }},
      {"policy negative enum", "spec.policy",
       [](S s) { s->set_policy(static_cast<v1::SimplifyPolicy>(-1)); }},
      {"error_tolerance NaN", "spec.error_tolerance", [](S s) { s->set_error_tolerance(kNaN); }},
      {"error_tolerance +inf", "spec.error_tolerance", [](S s) { s->set_error_tolerance(kInf); }},
      {"error_tolerance negative", "spec.error_tolerance", [](S s) { s->set_error_tolerance(-1); }},
      {"weights.regional negative", "spec.weights.regional",
       [](S s) { s->mutable_weights()->set_regional(-1); }},
      {"weights.gradient NaN", "spec.weights.gradient",
       [](S s) { s->mutable_weights()->set_gradient(kNaN); }},
      {"weights.shape +inf", "spec.weights.shape",
       [](S s) { s->mutable_weights()->set_shape(kInf); }},
      {"weights.volume -inf", "spec.weights.volume",
       [](S s) { s->mutable_weights()->set_volume(-kInf); }},
      {"weights.neighbour negative", "spec.weights.neighbour",
       [](S s) { s->mutable_weights()->set_neighbour(-0.5); }},
      {"views: unknown name", "spec.views", [](S s) { s->add_views("sideways"); }},
      {"views: 17 of them", "spec.views",
       [](S s) {
         for (int i = 0; i < 17; ++i) s->add_views("anterior");
       }},
      {"views: empty name", "spec.views", [](S s) { s->add_views(""); }},
      {"image_size 15", "spec.image_size", [](S s) { s->set_image_size(15); }},
      {"image_size 4097", "spec.image_size", [](S s) { s->set_image_size(4097); }},
      {"image_size explicitly 0", "spec.image_size", [](S s) { s->set_image_size(0); }},
      {"transfer_function unknown preset", "spec.transfer_function",
       [](S s) { s->set_transfer_function("no-such-preset"); }},
      {"transfer_function broken JSON", "spec.transfer_function",
       [](S s) { s->set_transfer_function("{not json"); }},
      {"interfaces unknown", "spec.interfaces", [](S s) { s->set_interfaces("voxel_faces"); }},
      {"interfaces wrong case", "spec.interfaces", [](S s) { s->set_interfaces("Free"); }},
      {"mesh_compression unknown", "spec.mesh_compression",
       [](S s) { s->set_mesh_compression("lz4"); }},
      {"mesh_compression wrong case", "spec.mesh_compression",
       [](S s) { s->set_mesh_compression("LZMA"); }},
      {"min_psnr NaN", "spec.min_psnr", [](S s) { s->set_min_psnr(kNaN); }},
      {"min_psnr +inf", "spec.min_psnr", [](S s) { s->set_min_psnr(kInf); }},
      {"min_psnr -inf", "spec.min_psnr", [](S s) { s->set_min_psnr(-kInf); }},
      {"min_psnr negative", "spec.min_psnr", [](S s) { s->set_min_psnr(-10); }},
      {"min_psnr 0", "spec.min_psnr", [](S s) { s->set_min_psnr(0); }},
      {"min_psnr with the paper policy", "spec.min_psnr",
       [](S s) {
         s->set_min_psnr(40);
         s->set_policy(v1::PAPER);
       }},
  };
}

}  // namespace decima::server
