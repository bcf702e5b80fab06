/* The one header bindgen reads (see build.rs). Debian 12 ships Embree 3.13.5;
 * building with `--features embree4` defines GS4CITY_EMBREE4 and uses Embree 4. */
#ifdef GS4CITY_EMBREE4
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif
