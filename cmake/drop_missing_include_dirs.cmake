# Passed to colcon as -DCMAKE_PROJECT_INCLUDE. The ROS 2 wheels export targets whose
# INTERFACE_INCLUDE_DIRECTORIES name the build machine's Python include directory, which
# does not exist here; CMake then refuses the imported target. At the end of the
# directory, drop the include entries that do not exist on this machine.
function(stance_drop_missing_include_dirs)
  get_property(targets DIRECTORY "${CMAKE_CURRENT_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT dirs)
      continue()
    endif()
    set(kept "")
    foreach(dir IN LISTS dirs)
      if(dir MATCHES "^\\$<" OR EXISTS "${dir}")
        list(APPEND kept "${dir}")
      endif()
    endforeach()
    set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${kept}")
  endforeach()
endfunction()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL stance_drop_missing_include_dirs)
