# Fix-up for building ROS 2 packages against the ros-jazzy-* PyPI wheels.
#
# The wheels' exported CMake target files (e.g.
# share/std_msgs/cmake/export_std_msgs__rosidl_generator_pyExport.cmake) name
# the include folders of the interpreter the wheels were built with
# (/opt/python/cp3XX-cp3XX/include/python3.X and .../numpy/_core/include).
# Those folders do not exist here, and CMake refuses to generate:
#   Imported target "..." includes non-existent path ...
#
# This file is injected with -DCMAKE_PROJECT_INCLUDE=<this file>, so the ROS
# package itself (orchard_mapping_msgs) stays a plain ament_cmake package that
# builds unchanged with colcon on a full ROS install. It defers a function to
# the end of configuring the top-level directory; the function walks every
# directory's imported targets and rewrites each non-existent Python / NumPy
# include folder to the local interpreter's ones (Python3_EXECUTABLE).
# Paths that exist, and paths that look like nothing Python-related, are kept.

include_guard(GLOBAL)
if(CMAKE_VERSION VERSION_LESS 3.21)  # IMPORTED_TARGETS directory property
  message(FATAL_ERROR "fix_wheel_includes needs CMake >= 3.21 (have ${CMAKE_VERSION})")
endif()

function(_owi_python_includes out_py out_np)
  set(_exe "${Python3_EXECUTABLE}")
  if(NOT _exe)
    find_package(Python3 QUIET COMPONENTS Interpreter)
    set(_exe "${Python3_EXECUTABLE}")
  endif()
  if(NOT _exe)
    message(FATAL_ERROR "fix_wheel_includes: no Python3_EXECUTABLE; pass -DPython3_EXECUTABLE=...")
  endif()
  execute_process(
    COMMAND "${_exe}" -c "import sysconfig; print(sysconfig.get_paths()['include'], end='')"
    OUTPUT_VARIABLE _py RESULT_VARIABLE _rc1)
  execute_process(
    COMMAND "${_exe}" -c "import numpy; print(numpy.get_include(), end='')"
    OUTPUT_VARIABLE _np RESULT_VARIABLE _rc2 ERROR_QUIET)
  if(NOT _rc1 EQUAL 0 OR NOT EXISTS "${_py}/Python.h")
    message(FATAL_ERROR "fix_wheel_includes: no Python.h under '${_py}' (${_exe}); install the Python development headers")
  endif()
  if(NOT _rc2 EQUAL 0)
    set(_np "")
  endif()
  set(${out_py} "${_py}" PARENT_SCOPE)
  set(${out_np} "${_np}" PARENT_SCOPE)
endfunction()

function(_owi_collect_dirs dir out)
  set(_all "${dir}")
  get_property(_subs DIRECTORY "${dir}" PROPERTY SUBDIRECTORIES)
  foreach(_s IN LISTS _subs)
    _owi_collect_dirs("${_s}" _sub_all)
    list(APPEND _all ${_sub_all})
  endforeach()
  set(${out} "${_all}" PARENT_SCOPE)
endfunction()

function(orchard_fix_wheel_includes)
  _owi_python_includes(_py_inc _np_inc)
  _owi_collect_dirs("${CMAKE_SOURCE_DIR}" _dirs)
  set(_fixed 0)
  foreach(_d IN LISTS _dirs)
    get_property(_targets DIRECTORY "${_d}" PROPERTY IMPORTED_TARGETS)
    foreach(_t IN LISTS _targets)
      get_target_property(_incs "${_t}" INTERFACE_INCLUDE_DIRECTORIES)
      if(NOT _incs)
        continue()
      endif()
      set(_new "")
      set(_changed FALSE)
      foreach(_i IN LISTS _incs)
        if(NOT _i MATCHES "\\$<" AND NOT EXISTS "${_i}")
          if(_i MATCHES "/numpy/(_core|core)/include/?$" AND _np_inc)
            set(_i "${_np_inc}")
            set(_changed TRUE)
          elseif(_i MATCHES "/include/python3\\.[0-9]+[a-z]*/?$")
            set(_i "${_py_inc}")
            set(_changed TRUE)
          endif()
        endif()
        list(APPEND _new "${_i}")
      endforeach()
      if(_changed)
        list(REMOVE_DUPLICATES _new)
        set_property(TARGET "${_t}" PROPERTY INTERFACE_INCLUDE_DIRECTORIES "${_new}")
        math(EXPR _fixed "${_fixed} + 1")
      endif()
    endforeach()
  endforeach()
  message(STATUS "fix_wheel_includes: rewrote Python/NumPy include folders of ${_fixed} imported target(s)")
endfunction()

cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL orchard_fix_wheel_includes)
