// Modbus register map of the PLC link (DESIGN.md "Modbus register map"): every address, bit and code as a constant.
#pragma once

#include <cstdint>
#include <limits>

// Addresses are 0-based PDU addresses (Modicon 4xxxx reference = address + 1). 32-bit and 64-bit values occupy
// consecutive registers, most significant word first. Change anything here only together with kMapVersion and
// README.md "PLC interface": PLC programs are written against these numbers.
namespace cellsight::drivers::modbus_map {

// Bumped on any change of this file a PLC program must know of; the PLC can read it at kMapVersionRegister.
// Version 2 appended the pose uncertainties and a second sequence copy (227-234) to the result block and left every
// version-1 address as it was, so a version-1 program that reads 200-226 still works.
inline constexpr std::uint16_t kMapVersion = 2;

// ---- blocks ----
// Command block: the PLC writes (FC06/FC16) and may read back (FC03). 5-9 are reserved and read back what was written.
inline constexpr std::uint16_t kCommandBlockFirst = 0;
inline constexpr std::uint16_t kCommandBlockCount = 10;
// Status block: read-only (FC03 or FC04). 111-119 are reserved and read 0.
inline constexpr std::uint16_t kStatusBlockFirst = 100;
inline constexpr std::uint16_t kStatusBlockCount = 20;
// Result block: read-only (FC03 or FC04), meant to be read whole in one request.
inline constexpr std::uint16_t kResultBlockFirst = 200;
inline constexpr std::uint16_t kResultBlockCount = 35;
// One array backs addresses 0..234; the gaps (10-99, 120-199) are never served.
inline constexpr std::uint16_t kRegisterSpan = kResultBlockFirst + kResultBlockCount;

// ---- command block (PLC writes) ----
inline constexpr std::uint16_t kControl = 0;
inline constexpr std::uint16_t kCommand = 1;
inline constexpr std::uint16_t kCommandArg = 2;  // u32, 2-3
inline constexpr std::uint16_t kPlcHeartbeat = 4;

// CONTROL bits.
inline constexpr std::uint16_t kControlTriggerEnable = 1u << 0;  // level
inline constexpr std::uint16_t kControlSwTrigger = 1u << 1;      // rising edge starts a pass
inline constexpr std::uint16_t kControlResultAck = 1u << 2;      // level, see the handshake
inline constexpr std::uint16_t kControlClearError = 1u << 3;     // rising edge
inline constexpr std::uint16_t kControlExecCmd = 1u << 4;        // rising edge latches COMMAND and ARG

// ---- status block (read-only) ----
inline constexpr std::uint16_t kStatus = 100;
inline constexpr std::uint16_t kHeartbeat = 101;
inline constexpr std::uint16_t kErrorCode = 102;
inline constexpr std::uint16_t kWarningCode = 103;
inline constexpr std::uint16_t kActiveModels = 104;
inline constexpr std::uint16_t kTriggerCount = 105;    // u32, 105-106
inline constexpr std::uint16_t kMissedTriggers = 107;  // u32, 107-108
inline constexpr std::uint16_t kResultQueueDepth = 109;
inline constexpr std::uint16_t kMapVersionRegister = 110;

// STATUS bits.
inline constexpr std::uint16_t kStatusReady = 1u << 0;
inline constexpr std::uint16_t kStatusTriggerReady = 1u << 1;
inline constexpr std::uint16_t kStatusTriggerAck = 1u << 2;
inline constexpr std::uint16_t kStatusBusy = 1u << 3;
inline constexpr std::uint16_t kStatusResultValid = 1u << 4;
inline constexpr std::uint16_t kStatusResultOverrun = 1u << 5;
inline constexpr std::uint16_t kStatusError = 1u << 6;
inline constexpr std::uint16_t kStatusWarning = 1u << 7;
inline constexpr std::uint16_t kStatusCmdDone = 1u << 8;
inline constexpr std::uint16_t kStatusCmdFailed = 1u << 9;
inline constexpr std::uint16_t kStatusPlcHbLost = 1u << 10;
inline constexpr std::uint16_t kStatusTeachMode = 1u << 11;

// HEARTBEAT advances by one per period and wraps at 65536.
inline constexpr std::int64_t kHeartbeatPeriodMs = 100;

// ---- result block (read-only) ----
inline constexpr std::uint16_t kResultSeq = 200;  // u32, 200-201; 0 = no result yet
inline constexpr std::uint16_t kAcqId = 202;      // u32, 202-203
inline constexpr std::uint16_t kResultCode = 204;
inline constexpr std::uint16_t kPartId = 205;
inline constexpr std::uint16_t kConfidence = 206;  // per mille
inline constexpr std::uint16_t kSource = 207;
inline constexpr std::uint16_t kPoseX = 208;      // s32 um, 208-209
inline constexpr std::uint16_t kPoseY = 210;      // s32 um, 210-211
inline constexpr std::uint16_t kPoseZ = 212;      // s32 um, 212-213
inline constexpr std::uint16_t kPoseRx = 214;     // s32 millidegrees, 214-215
inline constexpr std::uint16_t kPoseRy = 216;     // s32 millidegrees, 216-217
inline constexpr std::uint16_t kPoseRz = 218;     // s32 millidegrees, 218-219 (theta)
inline constexpr std::uint16_t kTimestamp = 220;  // u64 us CLOCK_MONOTONIC, 220-223
inline constexpr std::uint16_t kCycleMs = 224;
inline constexpr std::uint16_t kResultSeqCopy = 225;  // u32, 225-226; equal to 200-201 when 200-226 is whole
// 1-sigma uncertainty of each pose axis (version 2), u16; kInvalidSigma where the axis or its estimate is missing.
inline constexpr std::uint16_t kSigmaX = 227;   // um
inline constexpr std::uint16_t kSigmaY = 228;   // um
inline constexpr std::uint16_t kSigmaZ = 229;   // um
inline constexpr std::uint16_t kSigmaRx = 230;  // millidegrees
inline constexpr std::uint16_t kSigmaRy = 231;  // millidegrees
inline constexpr std::uint16_t kSigmaRz = 232;  // millidegrees (theta)
// u32, 233-234; written last, equal to 200-201 when the whole version-2 block 200-234 is whole.
inline constexpr std::uint16_t kResultSeqCopy2 = 233;

// A 32-bit value that is not available (pose not estimated, result without a pose).
inline constexpr std::int32_t kInvalidS32 = std::numeric_limits<std::int32_t>::min();  // 0x80000000
inline constexpr std::uint32_t kInvalidU32 = 0x80000000u;
// A sigma register that is not available (axis invalid, uncertainty not estimated, result without a pose).
inline constexpr std::uint16_t kInvalidSigma = 0xFFFF;
// The largest sigma on the wire: a larger finite one saturates here, so it never reads as "not available".
inline constexpr std::uint16_t kMaxSigma = 0xFFFE;

// ---- protocol limits (Modbus Application Protocol V1.1b3) ----
inline constexpr std::uint8_t kFcReadHoldingRegisters = 0x03;
inline constexpr std::uint8_t kFcReadInputRegisters = 0x04;
inline constexpr std::uint8_t kFcWriteSingleRegister = 0x06;
inline constexpr std::uint8_t kFcWriteMultipleRegisters = 0x10;
inline constexpr std::uint16_t kMaxReadQuantity = 125;
inline constexpr std::uint16_t kMaxWriteQuantity = 123;

inline constexpr std::uint8_t kExceptionIllegalFunction = 0x01;
inline constexpr std::uint8_t kExceptionIllegalDataAddress = 0x02;
inline constexpr std::uint8_t kExceptionIllegalDataValue = 0x03;

}  // namespace cellsight::drivers::modbus_map

namespace cellsight::drivers {

// RESULT_CODE (register 204).
enum class ResultCode : std::uint16_t {
  kOk = 0,
  kNoPart = 1,
  kUnknownPart = 2,
  kAmbiguous = 3,
  kPoseOutOfRange = 4,
  kBadScan = 5,
  kTimeout = 6,  // the 3 s deadline expired; never a guess
};

// SOURCE (register 207): which stage of the cascade decided.
enum class ResultSource : std::uint16_t { kNone = 0, kSvm = 1, kPerfectMatch = 2 };

// ERROR_CODE (register 102); STATUS.ERROR is set exactly when it is not kNone.
enum class ErrorCode : std::uint16_t {
  kNone = 0,
  kCameraFault = 1,           // camera missing, lost or streaming failed
  kCameraTimeout = 2,         // no frame arrived while scanning
  kIoFault = 3,               // GPIO (laser, trigger, photo-eye) failed
  kEncoderFault = 4,          // encoder unreadable or not counting while a part passes
  kCalibrationInvalid = 5,    // calibration missing, wrong version or checksum
  kModelDatabaseInvalid = 6,  // model database missing or refused (checksum/version)
  kConfigInvalid = 7,         // configuration refused at start-up or on a command
  kRepeatedTimeouts = 8,      // several consecutive cycles hit the hard deadline
  kInternal = 9,              // a programming error was caught; see the log
};

// WARNING_CODE (register 103); STATUS.WARNING is set exactly when it is not kNone.
enum class WarningCode : std::uint16_t {
  kNone = 0,
  kExposureAtLimit = 1,  // closed-loop exposure pinned at its minimum or maximum (coating too bright/dark)
  kCycleSlow = 2,        // cycle time above its budget, still inside the deadline
  kMissedTrigger = 3,    // a trigger arrived while busy (also counted in MISSED_TRIGGERS)
  kLowStorage = 4,       // little space left for logs and scans
};

// COMMAND (register 1), latched with ARG (2-3) on the EXEC_CMD rising edge.
enum class CommandCode : std::uint16_t {
  kNone = 0,
  kSelectModels = 1,  // ARG = model database id to activate (ACTIVE_MODELS follows)
  kEnterTeach = 2,    // ARG = PLC id of the part to teach; STATUS.TEACH_MODE follows
  kLeaveTeach = 3,
  kResetCounters = 4,  // TRIGGER_COUNT and MISSED_TRIGGERS back to 0
};

constexpr const char* to_string(ResultCode code) {
  switch (code) {
    case ResultCode::kOk: return "ok";
    case ResultCode::kNoPart: return "no part";
    case ResultCode::kUnknownPart: return "unknown part";
    case ResultCode::kAmbiguous: return "ambiguous";
    case ResultCode::kPoseOutOfRange: return "pose out of range";
    case ResultCode::kBadScan: return "bad scan";
    case ResultCode::kTimeout: return "timeout";
  }
  return "invalid";
}

constexpr const char* to_string(ErrorCode code) {
  switch (code) {
    case ErrorCode::kNone: return "none";
    case ErrorCode::kCameraFault: return "camera fault";
    case ErrorCode::kCameraTimeout: return "camera timeout";
    case ErrorCode::kIoFault: return "I/O fault";
    case ErrorCode::kEncoderFault: return "encoder fault";
    case ErrorCode::kCalibrationInvalid: return "calibration invalid";
    case ErrorCode::kModelDatabaseInvalid: return "model database invalid";
    case ErrorCode::kConfigInvalid: return "configuration invalid";
    case ErrorCode::kRepeatedTimeouts: return "repeated timeouts";
    case ErrorCode::kInternal: return "internal error";
  }
  return "invalid";
}

constexpr const char* to_string(WarningCode code) {
  switch (code) {
    case WarningCode::kNone: return "none";
    case WarningCode::kExposureAtLimit: return "exposure at limit";
    case WarningCode::kCycleSlow: return "cycle slow";
    case WarningCode::kMissedTrigger: return "missed trigger";
    case WarningCode::kLowStorage: return "low storage";
  }
  return "invalid";
}

}  // namespace cellsight::drivers
