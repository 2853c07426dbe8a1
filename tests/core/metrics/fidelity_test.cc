#include "core/metrics/fidelity.h"
#include <gtest/gtest.h>
