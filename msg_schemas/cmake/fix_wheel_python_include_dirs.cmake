# Repoint imported targets of the ROS 2 PyPI wheels at this machine's Python headers.
#
# The ros-jazzy-* wheels were built in a manylinux container whose interpreter lives in
# /opt/python/cp311-cp311. Their exported <pkg>::<pkg>__rosidl_generator_py targets keep that
# container's paths in INTERFACE_INCLUDE_DIRECTORIES:
#   /opt/python/cp311-cp311/include/python3.11
#   /opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include
# CMake refuses to generate build files for a target that links such an imported target
# ("Imported target ... includes non-existent path", "CMake Generate step failed").
#
# em_fix_wheel_python_include_dirs() replaces every non-existent entry of every imported target
# of the calling directory: a Python include folder (".../include/python3.X") becomes
# Python3_INCLUDE_DIRS and a NumPy include folder (".../numpy/_core/include" or
# ".../numpy/core/include") becomes Python3_NumPy_INCLUDE_DIRS, both as found for the
# interpreter given by Python3_EXECUTABLE. Any other missing path is a configure error, so
# a new kind of broken export is reported instead of silently kept.
#
# Call it after every find_package() and rosidl_generate_interfaces() of the directory:
# properties of imported targets are only read at the generate step.

cmake_minimum_required(VERSION 3.21)  # for the IMPORTED_TARGETS directory property

function(em_fix_wheel_python_include_dirs)
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
  get_directory_property(_targets IMPORTED_TARGETS)
  foreach(_target IN LISTS _targets)
    get_target_property(_dirs "${_target}" INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_fixed "")
    set(_changed FALSE)
    foreach(_dir IN LISTS _dirs)
      if(EXISTS "${_dir}" OR _dir MATCHES "^\\$<")
        # An existing folder, or a generator expression evaluated later: keep it.
        list(APPEND _fixed "${_dir}")
      elseif(_dir MATCHES "/include/python3\\.[0-9]+$")
        list(APPEND _fixed ${Python3_INCLUDE_DIRS})
        set(_changed TRUE)
      elseif(_dir MATCHES "/numpy/(_core|core)/include$")
        list(APPEND _fixed ${Python3_NumPy_INCLUDE_DIRS})
        set(_changed TRUE)
      else()
        message(FATAL_ERROR
          "Imported target ${_target} names the non-existent include folder '${_dir}', "
          "which em_fix_wheel_python_include_dirs() does not know how to replace.")
      endif()
    endforeach()
    if(_changed)
      list(REMOVE_DUPLICATES _fixed)
      set_target_properties("${_target}" PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_fixed}")
      message(STATUS "Repointed Python include folders of imported target ${_target}")
    endif()
  endforeach()
endfunction()
