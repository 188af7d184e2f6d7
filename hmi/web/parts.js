// The parts page (filled in by its module; see hmi/routes.hpp for its API's access rules).
'use strict';
