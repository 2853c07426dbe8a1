# Per-target build settings. Nothing here touches CMAKE_CXX_FLAGS: every flag is scoped to the
# targets that call decima_target_defaults().

function(decima_target_defaults target)
  decima_warnings(${target})
  decima_sanitize(${target})
endfunction()

function(decima_warnings target)
  target_compile_options(${target} PRIVATE -Wall -Wextra)
  if(DECIMA_WERROR)
    target_compile_options(${target} PRIVATE -Werror)
  endif()
endfunction()

# The sanitizer flags alone, also for generated code (decima_proto): every translation unit that
# inlines protobuf headers must agree on them, since protobuf's port_def.inc changes Map's
# behaviour under ThreadSanitizer (mixing gave a SEGV in map.h).
function(decima_sanitize target)
  if(DECIMA_SANITIZE_KIND STREQUAL "address")
    target_compile_options(${target} PRIVATE -fsanitize=address,undefined -fno-omit-frame-pointer
                                              -fno-sanitize-recover=undefined)
    # GCC 12 reports std::regex's std::function members as maybe-uninitialized once ASan's
    # instrumentation is in (a false positive in libstdc++ headers; cli_e2e_test).
    if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
      target_compile_options(${target} PRIVATE -Wno-maybe-uninitialized)
    endif()
    target_link_options(${target} PRIVATE -fsanitize=address,undefined)
    if(DECIMA_FUZZ)
      target_compile_options(${target} PRIVATE -fsanitize=fuzzer-no-link)
    endif()
  elseif(DECIMA_SANITIZE_KIND STREQUAL "thread")
    # gRPC, abseil, protobuf, SQLite and libgomp from Debian are not instrumented: run the tests
    # with TSAN_OPTIONS=suppressions=tests/tsan.supp and OMP_NUM_THREADS=1 (README).
    target_compile_options(${target} PRIVATE -fsanitize=thread -fno-omit-frame-pointer)
    target_link_options(${target} PRIVATE -fsanitize=thread)
  endif()
endfunction()

# decima_core_module(NAME SOURCES ... DEPS ...): one small library per core module, linked
# into the umbrella target decima_core.
function(decima_core_module name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(decima_${name} STATIC ${ARG_SOURCES})
  target_include_directories(decima_${name} PUBLIC ${PROJECT_SOURCE_DIR})
  target_link_libraries(decima_${name} PUBLIC ${ARG_DEPS} PRIVATE ${ARG_PRIVATE_DEPS})
  set_target_properties(decima_${name} PROPERTIES POSITION_INDEPENDENT_CODE ON)
  decima_warnings(decima_${name})
  # Under ThreadSanitizer the core stays uninstrumented, like the Debian libraries: its only
  # threads are OpenMP's (libgomp is not instrumented either, so the TSan tests run it on one
  # thread), and the service's concurrency lives in server/ and client/. The sanitizer build
  # then compiles in far less time, and the job processes of the service tests run at full speed
  # instead of several times slower. AddressSanitizer instruments the core as before.
  if(NOT DECIMA_SANITIZE_KIND STREQUAL "thread")
    decima_sanitize(decima_${name})
  endif()
  add_library(decima::${name} ALIAS decima_${name})
  set_property(GLOBAL APPEND PROPERTY DECIMA_CORE_MODULES decima_${name})
endfunction()

# decima_test_labels(TARGET LABEL...): records a test executable under its ctest labels, so that
# tests/CMakeLists.txt can offer one build target per label (tests-unit, tests-server, ...). The
# sanitizer CI builds only the labels it runs; with gtest_discover_tests an executable that was
# not built has no tests at all, so a list kept by hand could silently drop a new one.
function(decima_test_labels target)
  foreach(label IN LISTS ARGN)
    set_property(GLOBAL APPEND PROPERTY DECIMA_TEST_TARGETS_${label} ${target})
  endforeach()
endfunction()

# decima_test(NAME SOURCES ... DEPS ...): one GoogleTest executable registered with ctest.
function(decima_test name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS;LABELS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} decima_testing GTest::gtest GTest::gmock GTest::gtest_main)
  decima_target_defaults(${name})
  # Test files are drivers: what they test is compiled (and optimised) in the libraries. Unoptimised,
  # the GoogleTest- and gRPC-heavy files compile in about half the time (job_store_test.cc: 10 s
  # against 27 s), most of a CI build's time. After the configuration's flags, so it wins.
  target_compile_options(${name} PRIVATE -O0)
  decima_test_labels(${name} ${ARG_LABELS})
  gtest_discover_tests(${name} DISCOVERY_TIMEOUT 60
                       PROPERTIES LABELS "${ARG_LABELS}"
                                  ENVIRONMENT "DECIMA_SHARED_DATA=${DECIMA_SHARED_DATA}")
endfunction()
