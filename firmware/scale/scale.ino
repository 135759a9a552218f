// beadsight-scale: HX711 load cell on an Arduino -> one timestamped reading per line.
//
// Protocol (57600 baud, 8N1, lines end "\r\n"; see README.md in this folder):
//   boot / '?'   I,beadsight-scale,<version>,rate_hz=<10|80>,factor=<counts per gram>
//   reading      R,<seq>,<device_ms>,<grams with 2 decimals>
//   T            tare (average of 10 conversions)        -> OK T
//   C <grams>    calibrate with a known weight on it     -> OK C <factor>   (saved in EEPROM)
//   S <10|80>    output data rate (needs RATE wired)      -> OK S <rate>     (saved in EEPROM)
//   refused      ERR <reason>
//   diagnostics  # <text>
//
// Needs the "HX711 Arduino Library" by Bogdan Necula (bogde/HX711), version 0.7.5 or newer.

#include <Arduino.h>
#include <EEPROM.h>
#include "HX711.h"

// --- identity -------------------------------------------------------------------------
const char FIRMWARE_NAME[] = "beadsight-scale";
const char FIRMWARE_VERSION[] = "1.0.0";

// --- wiring (see README.md) -----------------------------------------------------------
const uint8_t DOUT_PIN = 2;  // HX711 DT / DOUT
const uint8_t SCK_PIN = 3;   // HX711 SCK / PD_SCK
const uint8_t RATE_PIN = 4;  // HX711 RATE (optional: many boards tie it to GND = 10 Hz)

// --- settings -------------------------------------------------------------------------
const long BAUD_RATE = 57600;                     // same as the reference sketch
const float DEFAULT_FACTOR = 545654.0 / 1175.0;   // counts per gram, the reference load cell
const uint8_t DEFAULT_RATE_HZ = 10;               // HX711 with RATE low
const uint8_t AVERAGE_SAMPLES = 10;               // conversions averaged by T and C
const long MIN_NET_COUNTS = 100;                  // C refuses a load smaller than this (~0.2 g)
const unsigned long NOT_READY_WARN_MS = 1000;     // warn when the HX711 is silent this long
const uint8_t COMMAND_MAX = 31;                   // longest command line accepted
const int EEPROM_ADDRESS = 0;
const uint32_t EEPROM_MAGIC = 0xBEAD5CA1UL;       // marks valid saved settings

struct Settings {
  uint32_t magic;
  float factor;
  uint8_t rateHz;
};

HX711 hx711;
Settings settings = {EEPROM_MAGIC, DEFAULT_FACTOR, DEFAULT_RATE_HZ};
long offsetCounts = 0;
uint32_t seq = 0;
unsigned long lastReadyMs = 0;
char command[COMMAND_MAX + 1];
uint8_t commandLength = 0;

void printInfo() {
  Serial.print(F("I,"));
  Serial.print(FIRMWARE_NAME);
  Serial.print(',');
  Serial.print(FIRMWARE_VERSION);
  Serial.print(F(",rate_hz="));
  Serial.print(settings.rateHz);
  Serial.print(F(",factor="));
  Serial.println(settings.factor, 2);
}

void loadSettings() {
  Settings stored;
  EEPROM.get(EEPROM_ADDRESS, stored);
  bool valid = stored.magic == EEPROM_MAGIC && stored.factor == stored.factor &&  // not NaN
               stored.factor != 0.0 && (stored.rateHz == 10 || stored.rateHz == 80);
  if (valid) {
    settings = stored;
  }
}

void saveSettings() {
  settings.magic = EEPROM_MAGIC;
  EEPROM.put(EEPROM_ADDRESS, settings);  // put() only writes bytes that changed
}

void applyRate() {
  digitalWrite(RATE_PIN, settings.rateHz == 80 ? HIGH : LOW);
  hx711.power_down();  // the new rate takes effect after a power cycle of the converter
  hx711.power_up();
}

// Average of n conversions, in ADC counts; false if the HX711 stops answering.
bool averageCounts(uint8_t n, long &result) {
  long long sum = 0;
  for (uint8_t i = 0; i < n; i++) {
    if (!hx711.wait_ready_timeout(NOT_READY_WARN_MS)) {
      return false;
    }
    sum += hx711.read();
  }
  result = (long)(sum / n);
  return true;
}

void tare() {
  long counts;
  if (!averageCounts(AVERAGE_SAMPLES, counts)) {
    Serial.println(F("ERR T hx711 not ready: check the wiring"));
    return;
  }
  offsetCounts = counts;
  Serial.println(F("OK T"));
}

void calibrate(const char *argument) {
  float knownGrams = atof(argument);
  if (!(knownGrams > 0.0)) {
    Serial.println(F("ERR C needs a positive weight in grams"));
    return;
  }
  long counts;
  if (!averageCounts(AVERAGE_SAMPLES, counts)) {
    Serial.println(F("ERR C hx711 not ready: check the wiring"));
    return;
  }
  long net = counts - offsetCounts;
  if (labs(net) < MIN_NET_COUNTS) {
    Serial.println(F("ERR C no load on the scale"));
    return;
  }
  settings.factor = (float)net / knownGrams;  // negative if the cell is mounted reversed
  saveSettings();
  Serial.print(F("OK C "));
  Serial.println(settings.factor, 2);
}

void setRate(const char *argument) {
  int rate = atoi(argument);
  if (rate != 10 && rate != 80) {
    Serial.println(F("ERR S rate must be one of 10, 80"));
    return;
  }
  settings.rateHz = (uint8_t)rate;
  saveSettings();
  applyRate();
  Serial.print(F("OK S "));
  Serial.println(rate);
}

void handleCommand(char *line) {
  while (*line == ' ') line++;
  char word = line[0];
  const char *argument = line[0] ? line + 1 : line;
  while (*argument == ' ') argument++;
  if (word == 'T' && line[1] == '\0') {
    tare();
  } else if (word == 'C' && line[1] == ' ') {
    calibrate(argument);
  } else if (word == 'S' && line[1] == ' ') {
    setRate(argument);
  } else if (word == '?' && line[1] == '\0') {
    printInfo();
  } else if (word != '\0') {
    Serial.print(F("ERR unknown command '"));
    Serial.print(line);
    Serial.println('\'');
  }
}

void pollSerial() {
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '\n' || c == '\r') {
      command[commandLength] = '\0';
      if (commandLength > 0) handleCommand(command);
      commandLength = 0;
    } else if (commandLength < COMMAND_MAX) {
      command[commandLength++] = c;
    }  // longer lines are truncated; the reply names what was understood
  }
}

void setup() {
  Serial.begin(BAUD_RATE);
  pinMode(RATE_PIN, OUTPUT);
  loadSettings();
  hx711.begin(DOUT_PIN, SCK_PIN);
  applyRate();
  long counts;
  if (averageCounts(AVERAGE_SAMPLES, counts)) {
    offsetCounts = counts;  // tare at boot, like the reference sketch
  } else {
    Serial.println(F("# hx711 not ready at boot: check the wiring; readings start when it answers"));
  }
  printInfo();
  seq = 0;
  lastReadyMs = millis();
}

void loop() {
  pollSerial();
  if (hx711.is_ready()) {
    unsigned long now = millis();
    long counts = hx711.read();
    float grams = (float)(counts - offsetCounts) / settings.factor;
    Serial.print(F("R,"));
    Serial.print(seq++);
    Serial.print(',');
    Serial.print(now);
    Serial.print(',');
    Serial.println(grams, 2);
    lastReadyMs = now;
  } else if (millis() - lastReadyMs > NOT_READY_WARN_MS) {
    Serial.println(F("# hx711 not ready: check the wiring"));
    lastReadyMs = millis();
  }
}
