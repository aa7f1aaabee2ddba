// lidarscan_roundtrip: the C++ side of tests/test_cpp.py.
//   lidarscan_roundtrip encode OUT   write the CDR bytes (rmw_serialize) of the scan below
//   lidarscan_roundtrip decode IN    rmw_deserialize IN and print every field, one per line
//   lidarscan_roundtrip pixels IN    rmw_deserialize IN, print the header and, per channel, its
//                                    name and every element read as its datatype in the
//                                    message's byte order (row-major, count values a pixel)
// The scan: 2 x 3, channels range (float32 metres, offset 0) and intensity (uint16, offset 24).
#include <algorithm>
#include <cinttypes>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "lidarscan_msgs/msg/lidar_scan.hpp"
#include "rcutils/allocator.h"
#include "rmw/error_handling.h"
#include "rmw/rmw.h"
#include "rmw/serialized_message.h"
#include "rosidl_typesupport_cpp/message_type_support.hpp"

namespace
{
using lidarscan_msgs::msg::LidarChannel;
using lidarscan_msgs::msg::LidarScan;

const rosidl_message_type_support_t * scan_type_support()
{
  return rosidl_typesupport_cpp::get_message_type_support_handle<LidarScan>();
}

LidarScan make_scan()
{
  LidarScan scan;
  scan.header.stamp.sec = 1700000000;
  scan.header.stamp.nanosec = 123456789;
  scan.header.frame_id = "os_lidar";
  scan.lidar_info_time.sec = 1699999999;
  scan.lidar_info_time.nanosec = 5;
  scan.height = 2;
  scan.width = 3;
  scan.is_bigendian = false;
  scan.is_destaggered = true;
  scan.column_time_offsets = {0, 33333, 66666};
  scan.column_azimuth_angles = {3.0, 1.0, -1.0};
  LidarChannel range;
  range.name = "range";
  range.offset = 0;
  range.datatype = LidarChannel::FLOAT32;
  range.count = 1;
  LidarChannel intensity;
  intensity.name = "intensity";
  intensity.offset = 24;
  intensity.datatype = LidarChannel::UINT16;
  intensity.count = 1;
  scan.channels = {range, intensity};
  const float ranges[6] = {1.5F, 2.25F, 3.0F, 0.5F, 100.0F, 7.125F};
  const uint16_t intensities[6] = {0, 1, 255, 256, 4096, 65535};
  scan.data.resize(40, 0);  // 24 + 12 bytes, padded to a multiple of 8
  std::memcpy(scan.data.data(), ranges, sizeof(ranges));  // little-endian host (x86-64)
  std::memcpy(scan.data.data() + 24, intensities, sizeof(intensities));
  return scan;
}

int fail(const char * what)
{
  std::fprintf(stderr, "error: %s: %s\n", what, rmw_get_error_string().str);
  return 1;
}

int encode(const char * path)
{
  LidarScan scan = make_scan();
  rmw_serialized_message_t out = rmw_get_zero_initialized_serialized_message();
  rcutils_allocator_t allocator = rcutils_get_default_allocator();
  if (rmw_serialized_message_init(&out, 0, &allocator) != RMW_RET_OK) {
    return fail("rmw_serialized_message_init");
  }
  if (rmw_serialize(&scan, scan_type_support(), &out) != RMW_RET_OK) {
    return fail("rmw_serialize");
  }
  std::ofstream file(path, std::ios::binary);
  file.write(reinterpret_cast<const char *>(out.buffer), static_cast<std::streamsize>(out.buffer_length));
  rmw_serialized_message_fini(&out);
  return file.good() ? 0 : 1;
}

bool read_scan(const char * path, LidarScan & scan)
{
  std::ifstream file(path, std::ios::binary);
  std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(file)), std::istreambuf_iterator<char>());
  rmw_serialized_message_t in = rmw_get_zero_initialized_serialized_message();
  in.buffer = bytes.data();
  in.buffer_length = bytes.size();
  in.buffer_capacity = bytes.size();
  in.allocator = rcutils_get_default_allocator();
  return rmw_deserialize(&in, scan_type_support(), &scan) == RMW_RET_OK;
}

void print_header(const LidarScan & scan)
{
  std::printf("stamp=%d %u\n", scan.header.stamp.sec, scan.header.stamp.nanosec);
  std::printf("frame_id=%s\n", scan.header.frame_id.c_str());
  std::printf("lidar_info_time=%d %u\n", scan.lidar_info_time.sec, scan.lidar_info_time.nanosec);
  std::printf("height=%u\nwidth=%u\n", scan.height, scan.width);
  std::printf("is_bigendian=%d\nis_destaggered=%d\n", scan.is_bigendian ? 1 : 0,
    scan.is_destaggered ? 1 : 0);
}

// One element of type T at p, stored big-endian or little-endian.
template<typename T>
T load(const uint8_t * p, bool big_endian)
{
  uint8_t b[sizeof(T)];
  std::memcpy(b, p, sizeof(T));
  const uint16_t one = 1;
  const bool host_big = *reinterpret_cast<const uint8_t *>(&one) == 0;
  if (big_endian != host_big) {
    std::reverse(b, b + sizeof(T));
  }
  T v;
  std::memcpy(&v, b, sizeof(T));
  return v;
}

size_t itemsize(uint8_t datatype)
{
  switch (datatype) {
    case LidarChannel::INT8: case LidarChannel::UINT8: return 1;
    case LidarChannel::INT16: case LidarChannel::UINT16: return 2;
    case LidarChannel::INT32: case LidarChannel::UINT32: case LidarChannel::FLOAT32: return 4;
    case LidarChannel::FLOAT64: return 8;
    default: return 0;
  }
}

void print_element(uint8_t datatype, const uint8_t * p, bool big)
{
  switch (datatype) {
    case LidarChannel::INT8: std::printf(" %d", static_cast<int>(static_cast<int8_t>(*p))); break;
    case LidarChannel::UINT8: std::printf(" %u", static_cast<unsigned>(*p)); break;
    case LidarChannel::INT16: std::printf(" %d", static_cast<int>(load<int16_t>(p, big))); break;
    case LidarChannel::UINT16: std::printf(" %u", static_cast<unsigned>(load<uint16_t>(p, big)));
      break;
    case LidarChannel::INT32: std::printf(" %" PRId32, load<int32_t>(p, big)); break;
    case LidarChannel::UINT32: std::printf(" %" PRIu32, load<uint32_t>(p, big)); break;
    case LidarChannel::FLOAT32: std::printf(" %.9g", static_cast<double>(load<float>(p, big)));
      break;
    case LidarChannel::FLOAT64: std::printf(" %.17g", load<double>(p, big)); break;
    default: break;
  }
}

int pixels(const char * path)
{
  LidarScan scan;
  if (!read_scan(path, scan)) {
    return fail("rmw_deserialize");
  }
  print_header(scan);
  const bool big = scan.is_bigendian;
  for (const auto & c : scan.channels) {
    const size_t size = itemsize(c.datatype);
    const size_t n = static_cast<size_t>(scan.height) * scan.width * c.count;
    if (size == 0 || c.offset + n * size > scan.data.size()) {
      std::fprintf(stderr, "error: channel %s: datatype %u, %zu elements from byte %u do not fit "
        "in %zu bytes of data\n", c.name.c_str(), static_cast<unsigned>(c.datatype), n, c.offset,
        scan.data.size());
      return 1;
    }
    std::printf("pixels=%s %u %u", c.name.c_str(), static_cast<unsigned>(c.datatype), c.count);
    const uint8_t * base = scan.data.data() + c.offset;
    for (size_t i = 0; i < n; ++i) {
      print_element(c.datatype, base + i * size, big);
    }
    std::printf("\n");
  }
  return 0;
}

int decode(const char * path)
{
  LidarScan scan;
  if (!read_scan(path, scan)) {
    return fail("rmw_deserialize");
  }
  print_header(scan);
  std::printf("column_time_offsets=");
  for (size_t i = 0; i < scan.column_time_offsets.size(); ++i) {
    std::printf("%s%" PRId64, i ? " " : "", scan.column_time_offsets[i]);
  }
  std::printf("\ncolumn_azimuth_angles=");
  for (size_t i = 0; i < scan.column_azimuth_angles.size(); ++i) {
    std::printf("%s%.17g", i ? " " : "", scan.column_azimuth_angles[i]);
  }
  std::printf("\n");
  for (const auto & c : scan.channels) {
    std::printf("channel=%s %u %u %u\n", c.name.c_str(), c.offset,
      static_cast<unsigned>(c.datatype), c.count);
  }
  std::printf("data=");
  for (uint8_t b : scan.data) {
    std::printf("%02x", b);
  }
  std::printf("\n");
  return 0;
}
}  // namespace

int main(int argc, char ** argv)
{
  if (argc != 3) {
    std::fprintf(stderr, "usage: %s encode OUT | decode IN | pixels IN\n", argv[0]);
    return 2;
  }
  if (std::strcmp(argv[1], "encode") == 0) {
    return encode(argv[2]);
  }
  if (std::strcmp(argv[1], "decode") == 0) {
    return decode(argv[2]);
  }
  if (std::strcmp(argv[1], "pixels") == 0) {
    return pixels(argv[2]);
  }
  std::fprintf(stderr, "unknown mode %s\n", argv[1]);
  return 2;
}
