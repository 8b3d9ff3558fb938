// A small OpenIGTLink receiver on the OpenIGTLink C++ library (Debian: libopenigtlink-dev),
// after the library's own examples/Receiver/ReceiveClient.cxx: an independent client of the
// humantele server. Usage: igtl_receiver HOST PORT COUNT. One line per message on stdout:
//   TRANSFORM <name> <crc_ok> <sec.frac> m00 m01 m02 m03 m10 ... m23
//   IMAGE <name> <crc_ok> <sec.frac> nx ny nz sx sy sz scalar_type first_nonzero_count
//   STRING <name> <crc_ok> <sec.frac> <text>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include "igtlClientSocket.h"
#include "igtlImageMessage.h"
#include "igtlMessageHeader.h"
#include "igtlStringMessage.h"
#include "igtlTransformMessage.h"

int main(int argc, char *argv[]) {
  if (argc != 4) { std::fprintf(stderr, "usage: igtl_receiver HOST PORT COUNT\n"); return 2; }
  igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
  if (socket->ConnectToServer(argv[1], std::atoi(argv[2])) != 0) {
    std::fprintf(stderr, "cannot connect\n"); return 1;
  }
  int count = std::atoi(argv[3]);
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  igtl::TimeStamp::Pointer ts = igtl::TimeStamp::New();
  for (int n = 0; n < count;) {
    header->InitPack();
    int r = socket->Receive(header->GetPackPointer(), header->GetPackSize());
    if (r == 0) break;
    if (r != header->GetPackSize()) continue;
    header->Unpack();
    header->GetTimeStamp(ts);
    double t = ts->GetTimeStamp();
    const char *type = header->GetDeviceType();
    if (std::strcmp(type, "TRANSFORM") == 0) {
      igtl::TransformMessage::Pointer msg = igtl::TransformMessage::New();
      msg->SetMessageHeader(header);
      msg->AllocatePack();
      socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize());
      int c = msg->Unpack(1);
      igtl::Matrix4x4 m;
      msg->GetMatrix(m);
      std::printf("TRANSFORM %s %d %.6f", msg->GetDeviceName(), (c & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0, t);
      for (int i = 0; i < 3; i++) for (int j = 0; j < 4; j++) std::printf(" %.6f", m[i][j]);
      std::printf("\n");
    } else if (std::strcmp(type, "IMAGE") == 0) {
      igtl::ImageMessage::Pointer msg = igtl::ImageMessage::New();
      msg->SetMessageHeader(header);
      msg->AllocatePack();
      socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize());
      int c = msg->Unpack(1);
      int size[3]; float spacing[3];
      msg->GetDimensions(size);
      msg->GetSpacing(spacing);
      const unsigned char *px = (const unsigned char *)msg->GetScalarPointer();
      long nonzero = 0;
      for (long i = 0; i < (long)size[0] * size[1] * size[2]; i++) nonzero += px[i] != 0;
      std::printf("IMAGE %s %d %.6f %d %d %d %.6f %.6f %.6f %d %ld\n", msg->GetDeviceName(),
                  (c & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0, t, size[0], size[1], size[2],
                  spacing[0], spacing[1], spacing[2], msg->GetScalarType(), nonzero);
    } else if (std::strcmp(type, "STRING") == 0) {
      igtl::StringMessage::Pointer msg = igtl::StringMessage::New();
      msg->SetMessageHeader(header);
      msg->AllocatePack();
      socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize());
      int c = msg->Unpack(1);
      std::printf("STRING %s %d %.6f %s\n", msg->GetDeviceName(),
                  (c & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0, t, msg->GetString());
    } else {
      socket->Skip(header->GetBodySizeToRead(), 0);
      continue;
    }
    std::fflush(stdout);
    n++;
  }
  socket->CloseSocket();
  return 0;
}
