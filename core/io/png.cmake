# PNG reading and writing (libpng stays inside core/io, see DESIGN.md). Included by
# core/io/CMakeLists.txt so the io module's owner can add it beside the volume readers.
decima_core_module(png SOURCES png.cc DEPS decima::common absl::status absl::statusor
                   PRIVATE_DEPS PNG::PNG ZLIB::ZLIB absl::strings)
