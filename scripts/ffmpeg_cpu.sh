#!/usr/bin/env bash
# The CPU seconds of every ffmpeg process a mosaic command starts, one line each in $FFMPEG_CPU_LOG
# (default /tmp/ffmpeg_cpu.log): user, system and wall seconds, then the command line.
#
#   IMAGEIO_FFMPEG_EXE=scripts/ffmpeg_cpu.sh /usr/bin/time mosaic stabilize in.mp4 out.mp4
#
# mosaic's own process is the command's total (/usr/bin/time) less these lines.
real=$(python3 -c "import imageio_ffmpeg, os; os.environ.pop('IMAGEIO_FFMPEG_EXE', None); print(imageio_ffmpeg.get_ffmpeg_exe())")
exec /usr/bin/time -a -o "${FFMPEG_CPU_LOG:-/tmp/ffmpeg_cpu.log}" -f "%U %S %e | %C" "$real" "$@"
