# Shared by the interface packages in interfaces/: what it takes to build an
# ament interface package with pip (scikit-build-core) inside a venv that holds
# the ros-jazzy-* wheels.

macro(cloneguard_use_venv_ros_prefix)
  # Built by pip (scikit-build-core) into a venv that holds the ros-jazzy-*
  # wheels.  The install prefix is then the wheel's staging "data" tree, so the
  # ROS prefix (the venv root, where share/<pkg>/cmake lives) has to be added to
  # the search paths by hand; ament's index lookups read AMENT_PREFIX_PATH.
  if(DEFINED SKBUILD)
    execute_process(
      COMMAND "${Python3_EXECUTABLE}" -c "import sys; print(sys.prefix)"
      OUTPUT_VARIABLE _ros_prefix
      OUTPUT_STRIP_TRAILING_WHITESPACE
      COMMAND_ERROR_IS_FATAL ANY)
    list(PREPEND CMAKE_PREFIX_PATH "${_ros_prefix}")
    if(DEFINED ENV{AMENT_PREFIX_PATH} AND NOT "$ENV{AMENT_PREFIX_PATH}" STREQUAL "")
      set(ENV{AMENT_PREFIX_PATH} "${_ros_prefix}:$ENV{AMENT_PREFIX_PATH}")
    else()
      set(ENV{AMENT_PREFIX_PATH} "${_ros_prefix}")
    endif()
  endif()
endmacro()

macro(cloneguard_drop_missing_include_dirs)
  # The wheels' exported *__rosidl_generator_py targets list the include dirs of
  # the manylinux image they were built in (/opt/python/cp311-cp311/...).  CMake
  # refuses imported targets whose include dirs do not exist, so drop those
  # entries; our own Python and NumPy include dirs are added by rosidl anyway.
  get_property(_imported DIRECTORY PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _imported)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept "")
    foreach(_dir IN LISTS _dirs)
      if(_dir MATCHES "^\\$<" OR EXISTS "${_dir}")
        list(APPEND _kept "${_dir}")
      endif()
    endforeach()
    set_property(TARGET ${_target} PROPERTY INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
  endforeach()
endmacro()
