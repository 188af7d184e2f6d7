// Forwarding include: Expected, Error and Status live in base/result.hpp, below algo/ (base/ cannot depend on algo/).
#pragma once

#include "base/result.hpp"
