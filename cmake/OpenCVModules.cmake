# Debian ships OpenCVConfig.cmake only in the libopencv-dev meta package (113 packages, incl. DNN
# and contrib); streetsim installs just the modules it uses and finds them here.
#   streetsim_find_opencv(core imgproc imgcodecs videoio)  ->  targets opencv::<module>
function(streetsim_find_opencv)
  find_path(STREETSIM_OPENCV_INCLUDE opencv2/core.hpp PATH_SUFFIXES opencv4 REQUIRED)
  foreach(module ${ARGN})
    if(NOT TARGET opencv::${module})
      find_library(STREETSIM_OPENCV_${module} opencv_${module} REQUIRED)
      add_library(opencv::${module} SHARED IMPORTED GLOBAL)
      set_target_properties(opencv::${module} PROPERTIES
        IMPORTED_LOCATION ${STREETSIM_OPENCV_${module}}
        INTERFACE_INCLUDE_DIRECTORIES ${STREETSIM_OPENCV_INCLUDE})
    endif()
  endforeach()
endfunction()
