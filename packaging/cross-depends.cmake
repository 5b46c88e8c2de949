# CPack project config for a cross build's package: the library dependencies dpkg-shlibdeps
# found for the native package, checked by scripts/package to be what these programs need.
if(NOT DEFINED ENV{PULSETRACK_DEB_DEPENDS})
  message(FATAL_ERROR "a cross build's package needs PULSETRACK_DEB_DEPENDS (scripts/package sets it)")
endif()
set(CPACK_DEBIAN_PACKAGE_DEPENDS "$ENV{PULSETRACK_DEB_DEPENDS}")
